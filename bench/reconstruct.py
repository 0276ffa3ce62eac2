"""Reconstruction speed: forms -> integrability -> one solve, per stage, 5K to 300K+ faces.

Each case runs in a fresh subprocess so its peak resident memory (ru_maxrss) is its own.
Meshes: icospheres (subdivisions 4..7) and the shared meshes. Two inputs per mesh:
"exact" (the mesh's own forms: integrable, solved by tree integration without a
factorization) and "noisy" (every dihedral angle perturbed by N(0, 1e-3) rad: not
integrable, so the system is factorized). Prints a markdown table and the fitted
scaling exponent of end-to-end time against face count (least squares on log-log), and
writes bench/out/reconstruct.json.

    python bench/reconstruct.py [--backend auto] [--quick]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "meshes"
OUT = ROOT / "bench" / "out"

CASES = ["icosphere:4", "decimated-knight.off", "bunny.off", "cactus.off", "bar.off",
         "rocker-arm.obj", "icosphere:5", "beetle.off", "stanford-bunny.obj", "armadillo.obj",
         "nefertiti.obj", "icosphere:6", "icosphere:7"]
QUICK = ["icosphere:4", "bunny.off", "rocker-arm.obj", "icosphere:5", "armadillo.obj"]


def load(case: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    if case.startswith("icosphere:"):
        mesh = trimesh.creation.icosphere(subdivisions=int(case.split(":")[1]))
    else:
        mesh = trimesh.load(SHARED / case, process=False)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def measure(case: str, backend: str, noisy: bool) -> dict:
    """Run one case in this process and return its timings."""
    sys.path.insert(0, str(ROOT))
    from solver import fundamental_forms, reconstruct

    V, F = load(case)
    t0 = time.perf_counter()
    forms = fundamental_forms(V, F)
    t1 = time.perf_counter()
    if noisy:
        rng = np.random.default_rng(0)
        inner = forms.angles != 0
        forms.angles[inner] += rng.normal(scale=1e-3, size=int(inner.sum()))
    result = reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                         backend=backend, n_vertices=len(V))
    t2 = time.perf_counter()
    X, Y = result.vertices - result.vertices.mean(0), V - V.mean(0)
    U, _, Vt = np.linalg.svd(X.T @ Y)
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    error = np.abs(X @ R - Y).max() / np.linalg.norm(np.ptp(V, axis=0))
    timings = result.report["timings"]
    return {"case": case, "input": "noisy" if noisy else "exact",
            "path": result.report["solve_path"], "vertices": len(V), "faces": len(F),
            "unknowns": result.report["n_unknowns"],
            "backend": result.report["backend"] or "-",
            "forms": t1 - t0, **{k: timings.get(k, 0.0) for k in
                                 ("validate", "assemble", "factorize", "solve")},
            "total": t2 - t0, "error": float(error),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--quick", action="store_true", help="five cases up to 90K faces")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--noisy", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(args.one, args.backend, args.noisy)))
        return
    rows = []
    print("| mesh | faces | unknowns | input | path | backend | forms | validate | assemble "
          "(incl. integrability) | factorize | solve | total s | peak RSS MB | rel. error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for case in QUICK if args.quick else CASES:
        for noisy in (False, True):
            command = [sys.executable, __file__, "--one", case, "--backend", args.backend]
            proc = subprocess.run(command + (["--noisy"] if noisy else []),
                                  capture_output=True, text=True, check=False)
            if proc.returncode:
                print(f"| {case} | failed: {proc.stderr.strip().splitlines()[-1]} |")
                continue
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            rows.append(r)
            print(f"| {r['case']} | {r['faces']} | {r['unknowns']} | {r['input']} | "
                  f"{r['path']} | {r['backend']} | {r['forms']:.2f} | {r['validate']:.2f} | "
                  f"{r['assemble']:.2f} | {r['factorize']:.2f} | {r['solve']:.2f} | "
                  f"{r['total']:.2f} | {r['peak_rss_mb']:.0f} | {r['error']:.1e} |",
                  flush=True)
    for kind in ("exact", "noisy"):
        chosen = [r for r in rows if r["input"] == kind]
        if len(chosen) >= 3:
            faces = np.log([r["faces"] for r in chosen])
            total = np.log([r["total"] for r in chosen])
            slope = np.polyfit(faces, total, 1)[0]
            print(f"\nFitted scaling exponent, {kind} forms (total time ~ faces^k): "
                  f"k = {slope:.2f}")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "reconstruct.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
