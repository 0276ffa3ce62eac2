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
* ``splits 1e-6``: as above at 1e-6 (edge-length ratios ~1e6).
* ``zero-area``: 1 edge in 500 with a zero-area face inserted on it (a vertex on the edge,
  :func:`tests.helpers.meshes.with_zero_area_faces`) and 1 face in 2000 with collinear
  corners (a corner moved onto its opposite edge).
* ``scan-like`` (rocker-arm only): the held-out scan of issue 40 as described there (69K
  faces, genus 1, 3 zero-area faces, ~6% of faces with a corner under 5 degrees, edge-length
  ratio ~1.8e4), built from rocker-arm (genus 1) subdivided once (80K faces), 1 edge in 30
  split at 5e-3 of its length (ratio 2e4) and 3 inserted zero-area faces.

For each: the exact forms (does the default answer refine? its time against the linear
answer's) and the forms with N(0, 1e-3) rad on every interior dihedral angle (converged?
iterations, factorizations, time x linear, and the largest form error on the well-shaped
elements, :func:`solver.refine.form_energy.well_shaped_errors`, of the refinement's start and of
its answer: the answer's must not be larger). Times are wall-clock medians of ``--repeat``
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
from solver.mesh.topology import build_topology
from tests.helpers.meshes import with_cap_faces, with_tiny_edges, with_zero_area_faces

MESHES = ("rocker-arm.obj", "stanford-bunny.obj")
LARGE = ("nefertiti.obj",)


def scan_like(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The held-out scan of issue 40 as described (see the module docstring)."""
    import trimesh

    V, F = trimesh.remesh.subdivide(V, F)
    V, F = with_tiny_edges(V, F, len(F) // 30, ratio=5e-3, seed=7)
    return with_zero_area_faces(V, F, 3, seed=8, at=0.37)


def stand_ins(name: str, V: np.ndarray, F: np.ndarray,
              ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The family of irregular versions of one mesh."""
    import igl

    m = len(F)
    decimated = igl.decimate(V, F, m // 4)
    inserted = with_zero_area_faces(V, F, m // 500, seed=2, at=0.3)
    family = {
        "splits 1e-4": with_tiny_edges(V, F, m // 200, ratio=1e-4, seed=0),
        "splits 1e-5": with_tiny_edges(V, F, m // 200, ratio=1e-5, seed=1),
        "splits 1e-6": with_tiny_edges(V, F, m // 200, ratio=1e-6, seed=2),
        "caps": (with_cap_faces(V, F, m // 2000, height=1e-6), F),
        "zero-area": (with_cap_faces(*inserted, m // 2000, height=0.0, seed=4), inserted[1]),
        "decimated": (np.asarray(decimated[0], dtype=np.float64),
                      np.asarray(decimated[1], dtype=np.int64)),
    }
    if name == "rocker-arm.obj":
        family["scan-like"] = scan_like(V, F)
    return family


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
    guard = refinement.get("well_shaped_error", {})
    return {"linear": float(np.median(linear)), "default": float(np.median(default)),
            "well": (f"{guard['start']:.1e} / {guard['refined']:.1e}" if guard else "-"),
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
          "converged | iterations / factorizations | well-shaped error start / answer | "
          "linear s | default s | x linear |")
    print("|---|---|---:|---:|---:|---|---|---|---:|---:|---:|---:|---:|")
    for name in args.meshes or MESHES + (LARGE if args.large else ()):
        V, F = load_bench_mesh(name)
        for label, (U, G) in stand_ins(name, V, F).items():
            shape = irregularity(U, G)
            try:
                forms = solver.fundamental_forms(U, G)
            except solver.SolverInputError as exc:
                print(f"| {name} | {label} | {len(G)} | {shape['ratio']:.1e} | "
                      f"{shape['under5']:.1%} | {exc.kind} | | | | | | | |")
                continue
            inner = build_topology(forms.faces).interior_edges
            noisy = forms.angles.copy()
            noisy[inner] += np.random.default_rng(0).normal(0, 1e-3, len(inner))
            for kind, angles in (("exact", forms.angles), ("noisy", noisy)):
                r = measure(forms, angles, args.repeat)
                print(f"| {name} | {label} | {len(G)} | {shape['ratio']:.1e} | "
                      f"{shape['under5']:.1%} | {kind} | {r['refined']} | {r['converged']} "
                      f"({r['stop']}) | {r['iterations']} / {r['factorizations']} | "
                      f"{r['well']} | {r['linear']:.2f} | {r['default']:.2f} | "
                      f"{r['default'] / r['linear']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
