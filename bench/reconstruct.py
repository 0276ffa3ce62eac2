"""Reconstruction speed per stage, cold and warm, against SciPy SuperLU in the same run.

Each mesh runs in a fresh subprocess (so "cold" means an empty analysis cache and the
peak memory is the case's own). Inputs: the mesh's own forms ("exact": integrable, solved
by tree integration) and the same forms with every dihedral angle perturbed by
N(0, 1e-3) rad ("noisy": the |V| + 3|F| system is factorized). For the noisy forms, in
this order, in one process:

* ``pardiso cold``: ``reconstruct(..., refine=False)`` with an empty analysis cache;
* ``pardiso warm``: the same call again (same connectivity: the analysis is reused);
* ``refined``: the default answer (``refine=None``: Levenberg-Marquardt after the linear
  solve), warm;
* ``superlu``: ``reconstruct(..., backend="superlu", refine=False)`` -- the reference;
* ``superlu refined``: the default answer with ``backend="superlu"`` (every factorization
  of the linear path and of the refinement by SuperLU): the reference of the refined
  answer, measured up to :data:`SUPERLU_REFINED_MAX_FACES` faces (beyond, it takes minutes);
* the linear algebra alone on the very matrix the linear path factorizes: PARDISO cold
  (analysis = ordering + symbolic factorization, numerical factorization, 3-RHS solve),
  warm (a dead factorization's analysed handle reused: numerical factorization + solve)
  and ``scipy.sparse.linalg.splu`` with the MMD ordering on K + K^T (the ``superlu``
  backend's settings) + solve.

Ratios are reference time / our time, so they hold on a loaded machine as long as both
ran in the same process minutes apart. Also: ``Deformer`` set-up on the 20K-face
rocker-arm, cold and with a new handle set on the same mesh. Prints markdown tables and
the fitted scaling exponents (time ~ faces^k, least squares on log-log); writes
``bench/out/reconstruct.json``.

    python -m bench.reconstruct [--quick] [--cases name ...] [--threads 1]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import subprocess
import sys
import time
from typing import Any

import numpy as np

from bench.common import REPO, load_bench_mesh, scaling_exponent

OUT = REPO / "bench" / "out"

CASES = ["icosphere:4", "bunny.off", "rocker-arm.obj", "icosphere:5", "beetle.off",
         "stanford-bunny.obj", "armadillo.obj", "nefertiti.obj", "icosphere:6"]
QUICK = ["icosphere:4", "rocker-arm.obj", "armadillo.obj", "nefertiti.obj"]
DEFORM_MESH = "rocker-arm.obj"
SUPERLU_REFINED_MAX_FACES = 30_000


def _peak_reset() -> None:
    """Reset the kernel's peak-RSS mark (VmHWM) of this process to its current RSS."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass


def _peak_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _timed(label: str, call: Any, out: dict[str, Any]) -> Any:
    """Run ``call()``; store its wall time (s) and the peak RSS (MB) reached under label."""
    gc.collect()
    _peak_reset()
    start = time.perf_counter()
    result = call()
    out[label] = {"seconds": time.perf_counter() - start, "peak_mb": _peak_mb()}
    return result


def _reconstruct_row(result: Any, timing: dict[str, Any]) -> dict[str, Any]:
    report = result.report
    return {**timing, "stages": {k: float(v) for k, v in report["timings"].items()},
            "analysis": report.get("analysis", "?"), "path": report["solve_path"],
            "backend": report["backend"],
            "refined": bool(report.get("refinement", {}).get("refined", False))}


def measure_reconstruct(case: str) -> dict[str, Any]:
    """Every measurement of one mesh, in this process."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from solver import fundamental_forms, linalg, reconstruct
    from solver.immersion import ImmersionProblem
    from solver.linear.system import unknown_groups
    from solver.mesh.topology import build_topology

    linalg.clear_analysis_cache()
    V, F = load_bench_mesh(case)
    forms = fundamental_forms(V, F)
    row: dict[str, Any] = {"case": case, "vertices": len(V), "faces": len(F),
                           "load_start": os.getloadavg()[0]}

    def run(angles: np.ndarray, **kw: Any) -> Any:
        return reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                           n_vertices=len(V), **kw)

    timing: dict[str, Any] = {}
    exact = _timed("exact", lambda: run(forms.angles, refine=False), timing)
    row["exact"] = _reconstruct_row(exact, timing["exact"])
    noisy = forms.angles.copy()
    inner = noisy != 0
    noisy[inner] += np.random.default_rng(0).normal(scale=1e-3, size=int(inner.sum()))
    for label, kw in (("pardiso cold", {"backend": "pardiso", "refine": False}),
                      ("pardiso warm", {"backend": "pardiso", "refine": False}),
                      ("refined", {"backend": "pardiso"}),
                      ("superlu", {"backend": "superlu", "refine": False}),
                      ("superlu refined", {"backend": "superlu"})):
        if label == "superlu refined" and len(F) > SUPERLU_REFINED_MAX_FACES:
            continue
        result = _timed(label, lambda kw=kw: run(noisy, **kw), timing)
        row[label] = _reconstruct_row(result, timing[label])
        row["unknowns"] = result.report["n_unknowns"]
        del result

    # The linear algebra alone, on the matrix the linear path factorizes.
    problem = ImmersionProblem(build_topology(forms.faces, n_vertices=len(V)),
                               forms.lengths, noisy)
    anchor, _ = problem.anchors(np.ones(problem.topology.n_components, dtype=bool))
    matrix = sp.csr_array(problem.system(anchor, "superlu").factor._matrix)
    groups = unknown_groups(len(V), len(F))  # the ordering hint the product passes
    rhs = np.random.default_rng(1).normal(size=(matrix.shape[0], 3))
    linalg.clear_analysis_cache()
    algebra: dict[str, Any] = {"nnz": int(matrix.nnz)}
    for label in ("pardiso cold", "pardiso warm"):
        gc.collect()
        _peak_reset()
        start = time.perf_counter()
        fact = linalg.factorize(matrix, "pardiso", assume_symmetric=True, groups=groups)
        mid = time.perf_counter()
        fact.solve(rhs)
        algebra[label] = {"total": time.perf_counter() - start, "solve": time.perf_counter() - mid,
                          **fact.timings, "analysis_state": fact.analysis,
                          "peak_mb": _peak_mb()}
        del fact
    gc.collect()
    _peak_reset()
    csc = sp.csc_array(matrix)
    start = time.perf_counter()
    lu = splu(csc, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
              options={"SymmetricMode": True})
    mid = time.perf_counter()
    lu.solve(rhs)
    algebra["superlu"] = {"total": time.perf_counter() - start, "factorization": mid - start,
                          "solve": time.perf_counter() - mid, "peak_mb": _peak_mb()}
    row["linear_algebra"] = algebra
    row["load_end"] = os.getloadavg()[0]
    return row


def measure_deformer(case: str, warm_backend: bool = False) -> dict[str, Any]:
    """``Deformer`` set-up cold, then a new handle set on the same mesh (first dropped),
    then another while the previous one is still alive. ``warm_backend``: load MKL and
    start its threads first with a 2x2 factorization (what a service worker has done
    before its first request), so "cold" is only the new mesh's cost."""
    import scipy.sparse as sp

    from solver import Deformer, linalg

    if warm_backend:
        linalg.factorize(sp.identity(2, format="csr"), "pardiso").solve(np.ones(2))
    linalg.clear_analysis_cache()
    V, F = load_bench_mesh(case)
    rng = np.random.default_rng(0)
    sets = [rng.choice(len(V), size=400, replace=False) for _ in range(3)]
    out: dict[str, Any] = {"case": case, "faces": len(F), "load_start": os.getloadavg()[0]}
    first = _timed("cold", lambda: Deformer(V, F, sets[0], backend="pardiso"), out)
    out["cold"]["analysis"] = first.system.analysis
    del first
    second = _timed("new handles", lambda: Deformer(V, F, sets[1], backend="pardiso"), out)
    out["new handles"]["analysis"] = second.system.analysis
    third = _timed("new handles, previous alive",
                   lambda: Deformer(V, F, sets[2], backend="pardiso"), out)
    out["new handles, previous alive"]["analysis"] = third.system.analysis
    del second, third
    out["load_end"] = os.getloadavg()[0]
    return out


def _subprocess(*args: str, threads: int | None = None) -> dict[str, Any] | str:
    env = dict(os.environ)
    if threads:
        env.update(MKL_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
    proc = subprocess.run([sys.executable, "-m", "bench.reconstruct", *args],
                          capture_output=True, text=True, check=False, env=env, cwd=REPO)
    if proc.returncode:
        return (proc.stderr.strip().splitlines() or ["?"])[-1]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _ratio(reference: float, ours: float) -> str:
    return f"{reference / ours:.1f}x"


def print_tables(rows: list[dict[str, Any]], deformer: dict[str, Any] | str) -> None:
    print("\nEnd to end, noisy forms (s; ratio = superlu / pardiso, same process):\n")
    print("| mesh | faces | unknowns | load | superlu | pardiso cold | ratio | analysis | "
          "pardiso warm | ratio | analysis | refined (warm) | ratio | exact (tree) |")
    print("|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---|---:|---:|---:|")
    for r in rows:
        ref = r["superlu"]["seconds"]
        cold, warm, ref_d = r["pardiso cold"], r["pardiso warm"], r["refined"]
        print(f"| {r['case']} | {r['faces']} | {r['unknowns']} | "
              f"{r['load_start']:.1f}-{r['load_end']:.1f} | {ref:.2f} | {cold['seconds']:.2f} | "
              f"{_ratio(ref, cold['seconds'])} | {cold['analysis']} | {warm['seconds']:.2f} | "
              f"{_ratio(ref, warm['seconds'])} | {warm['analysis']} | {ref_d['seconds']:.2f} | "
              f"{_ratio(ref, ref_d['seconds'])} | {r['exact']['seconds']:.2f} |")
    print("\nThe refined (default) answer against the same refinement with SuperLU "
          f"(up to {SUPERLU_REFINED_MAX_FACES} faces; s, ratio = superlu / pardiso):\n")
    print("| mesh | faces | superlu refined | pardiso refined | ratio |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        if "superlu refined" not in r:
            continue
        ref, ours = r["superlu refined"]["seconds"], r["refined"]["seconds"]
        print(f"| {r['case']} | {r['faces']} | {ref:.2f} | {ours:.2f} | {_ratio(ref, ours)} |")
    print("\nStages of the linear path (s): validate / assemble / factorize / solve\n")
    print("| mesh | superlu | pardiso cold | pardiso warm | peak MB superlu / cold / warm |")
    print("|---|---|---|---|---|")
    for r in rows:
        def st(key: str, r: dict[str, Any] = r) -> str:
            s = r[key]["stages"]
            return " / ".join(f"{s.get(k, 0.0):.2f}" for k in
                              ("validate", "assemble", "factorize", "solve"))
        print(f"| {r['case']} | {st('superlu')} | {st('pardiso cold')} | {st('pardiso warm')} | "
              f"{r['superlu']['peak_mb']:.0f} / {r['pardiso cold']['peak_mb']:.0f} / "
              f"{r['pardiso warm']['peak_mb']:.0f} |")
    print("\nLinear algebra alone on the same matrix (s; factorize + 3-RHS solve; "
          "ratio = splu / pardiso):\n")
    print("(PARDISO with the ordering hint the product passes. The warm ratio is what a free "
          "analysis would give, and validation and assembly cost the same on both sides: so "
          "no end-to-end ratio of the linear path, cold or warm, can exceed the warm ratio "
          "here, beyond the timing noise.)\n")
    print("| mesh | N | nnz | splu MMD (fact + solve) | pardiso cold: analysis + numeric + "
          "solve | ratio | pardiso warm: numeric + solve | ratio | peak MB splu / cold |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        a = r["linear_algebra"]
        ref, cold, warm = a["superlu"], a["pardiso cold"], a["pardiso warm"]
        print(f"| {r['case']} | {r['unknowns']} | {a['nnz']} | {ref['factorization']:.2f} + "
              f"{ref['solve']:.2f} | {cold['analysis']:.2f} + {cold['factorization']:.2f} + "
              f"{cold['solve']:.2f} | {_ratio(ref['total'], cold['total'])} | "
              f"{warm['factorization']:.2f} + {warm['solve']:.2f} "
              f"({warm['analysis_state']}) | {_ratio(ref['total'], warm['total'])} | "
              f"{ref['peak_mb']:.0f} / {cold['peak_mb']:.0f} |")
    if len(rows) >= 3:
        faces = [r["faces"] for r in rows]
        print()
        for key in ("exact", "pardiso cold", "pardiso warm", "refined", "superlu"):
            slope = scaling_exponent(faces, [r[key]["seconds"] for r in rows])
            print(f"Fitted scaling exponent, {key} (end-to-end time ~ faces^k): k = {slope:.2f}")
    print(f"\nDeformer set-up ({DEFORM_MESH}, 400 handles, whole mesh):\n")
    if isinstance(deformer, str):
        print(f"failed: {deformer}")
        return
    print(f"load {deformer['load_start']:.1f}-{deformer['load_end']:.1f}\n")
    print("| set-up | seconds | analysis | peak MB |")
    print("|---|---:|---|---:|")
    for key in ("cold", "new handles", "new handles, previous alive"):
        d = deformer[key]
        print(f"| {key} | {d['seconds']:.3f} | {d['analysis']} | {d['peak_mb']:.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    parser.add_argument("--cases", nargs="*", help="mesh names (default: all)")
    parser.add_argument("--threads", type=int, help="MKL_NUM_THREADS of the measured "
                        "processes (default: MKL's, one per core)")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--deformer", help=argparse.SUPPRESS)
    parser.add_argument("--warm-backend", action="store_true",
                        help="with --deformer: load MKL before the cold set-up, as a "
                             "service worker has")
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure_reconstruct(args.one)))
        return
    if args.deformer:
        print(json.dumps(measure_deformer(args.deformer, args.warm_backend)))
        return
    print(f"load average at start: {os.getloadavg()}; MKL threads: {args.threads or 'default'}")
    rows = []
    for case in args.cases or (QUICK if args.quick else CASES):
        row = _subprocess("--one", case, threads=args.threads)
        if isinstance(row, str):
            print(f"{case}: failed: {row}")
            continue
        rows.append(row)
        print(f"{case}: done (load {row['load_end']:.1f})", flush=True)
    deformer = _subprocess("--deformer", DEFORM_MESH, threads=args.threads)
    print_tables(rows, deformer)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "reconstruct.json").write_text(json.dumps({"rows": rows, "deformer": deformer},
                                                     indent=2))


if __name__ == "__main__":
    main()
