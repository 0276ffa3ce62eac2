"""Slivers do not cost (issue 40): a family of irregular stand-ins, exact and noisy forms,
the default (refined) answer against the linear answer of the same forms, in one run.

Stand-ins, each on several shared meshes (rocker-arm 20K faces, stanford-bunny 69K;
``--large`` adds nefertiti, 100K):

* ``splits 1e-4`` / ``splits 1e-5``: 1 edge in 200 (no two sharing a face) split at 1e-4 or
  1e-5 of its length from an endpoint (:func:`tests.helpers.meshes.with_tiny_edges`): a tiny
  edge and two needles each; edge-length ratios ~1e4 and ~1e5.
* ``caps``: 1 face in 2000 flattened to 1e-6 of its width (a corner of nearly 180 degrees,
  :func:`tests.helpers.meshes.with_cap_faces`).
* ``decimated``: libigl's edge-collapse decimation to a quarter of the faces (slivers as
  aggressive decimation leaves them).

For each: the exact forms (does the default answer refine? its time against the linear
answer's) and the forms with N(0, 1e-3) rad on every interior dihedral angle (converged?
iterations, factorizations, time x linear). Times are wall-clock medians of ``--repeat``
alternating runs, warm (a first call on the mesh primes the analysis caches).
The targets: exact forms never refine; noisy forms converge within 2.5x the linear time and
at most 4 factorizations.

    python -m bench.slivers [--large] [--repeat 1] [--meshes rocker-arm.obj ...]
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

import solver
from bench.common import load_bench_mesh
from solver.topology import build_topology
from tests.helpers.meshes import with_cap_faces, with_tiny_edges

MESHES = ("rocker-arm.obj", "stanford-bunny.obj")
LARGE = ("nefertiti.obj",)


def stand_ins(V: np.ndarray, F: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The family of irregular versions of one mesh."""
    import igl

    m = len(F)
    decimated = igl.decimate(V, F, m // 4)
    return {
        "splits 1e-4": with_tiny_edges(V, F, m // 200, ratio=1e-4, seed=0),
        "splits 1e-5": with_tiny_edges(V, F, m // 200, ratio=1e-5, seed=1),
        "caps": (with_cap_faces(V, F, m // 2000, height=1e-6), F),
        "decimated": (np.asarray(decimated[0], dtype=np.float64),
                      np.asarray(decimated[1], dtype=np.int64)),
    }


def irregularity(V: np.ndarray, F: np.ndarray) -> dict[str, float]:
    """Edge-length ratio and the share of faces with a corner under 5 degrees."""
    e = np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2)
    a, b, c = e[:, 0], e[:, 1], e[:, 2]
    cos = np.clip(np.stack([(a**2 + c**2 - b**2) / (2 * a * c), (a**2 + b**2 - c**2) / (2 * a * b),
                            (b**2 + c**2 - a**2) / (2 * b * c)], axis=1), -1, 1)
    smallest = np.degrees(np.arccos(cos)).min(axis=1)
    return {"ratio": float(e.max() / e.min()), "under5": float(np.mean(smallest < 5.0))}


def timed(forms: solver.Forms, angles: np.ndarray, **options: Any) -> tuple[float, Any]:
    start = time.perf_counter()
    result = solver.reconstruct(forms.faces, forms.edges, forms.lengths, angles, **options)
    return time.perf_counter() - start, result


def measure(forms: solver.Forms, angles: np.ndarray, repeat: int) -> dict[str, Any]:
    """Linear and default answers of the same forms, alternating, medians."""
    timed(forms, angles, refine=False)  # warm: analyses cached
    linear, default, result = [], [], None
    for _ in range(repeat):
        linear.append(timed(forms, angles, refine=False)[0])
        seconds, result = timed(forms, angles)
        default.append(seconds)
    refinement = result.report["refinement"]
    return {"linear": float(np.median(linear)), "default": float(np.median(default)),
            "refined": refinement["refined"], "converged": refinement.get("converged", "-"),
            "stop": refinement.get("stop_reason", refinement.get("reason", "")),
            "iterations": refinement.get("iterations", 0),
            "factorizations": refinement.get("factorizations", 0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--large", action="store_true")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--meshes", nargs="+", default=None,
                        help="shared meshes instead of the default ones")
    args = parser.parse_args()
    print("| mesh | stand-in | faces | length ratio | corners < 5 deg | forms | refined? | "
          "converged | iterations / factorizations | linear s | default s | x linear |")
    print("|---|---|---:|---:|---:|---|---|---|---:|---:|---:|---:|")
    for name in args.meshes or MESHES + (LARGE if args.large else ()):
        V, F = load_bench_mesh(name)
        for label, (U, G) in stand_ins(V, F).items():
            shape = irregularity(U, G)
            try:
                forms = solver.fundamental_forms(U, G)
            except solver.SolverInputError as exc:
                print(f"| {name} | {label} | {len(G)} | {shape['ratio']:.1e} | "
                      f"{shape['under5']:.1%} | {exc.kind} | | | | | | |")
                continue
            inner = build_topology(forms.faces).interior_edges
            noisy = forms.angles.copy()
            noisy[inner] += np.random.default_rng(0).normal(0, 1e-3, len(inner))
            for kind, angles in (("exact", forms.angles), ("noisy", noisy)):
                r = measure(forms, angles, args.repeat)
                print(f"| {name} | {label} | {len(G)} | {shape['ratio']:.1e} | "
                      f"{shape['under5']:.1%} | {kind} | {r['refined']} | {r['converged']} "
                      f"({r['stop']}) | {r['iterations']} / {r['factorizations']} | "
                      f"{r['linear']:.2f} | {r['default']:.2f} | "
                      f"{r['default'] / r['linear']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
