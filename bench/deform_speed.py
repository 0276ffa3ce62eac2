"""Per-drag deformation latency against libigl's ARAP, side by side on a ~20K-face mesh.

Ours: `solver.Deformer` factorizes once (setup), then each drag is `deformer.solve`
(back-substitution only; with orthonormalize, two back-substitutions and a batched polar
projection). libigl: `igl.arap_precomputation` once, then `igl.arap_solve` with 10
iterations per drag (the usual interactive setting). Whole mesh as ROI, the same handle
vertices for both, 30 drags of random handle displacements.

    pip install libigl      # bench-only extra: pip install -e ".[bench]"
    python -m bench.deform_speed [mesh]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from bench.common import load_bench_mesh, random_drags, two_handle_regions
from solver import Deformer

DRAGS = 30


def time_ours(V, F, handles, moves, orthonormalize: bool) -> tuple[float, float, str]:
    t0 = time.perf_counter()
    deformer = Deformer(V, F, handles, orthonormalize=orthonormalize)
    setup = time.perf_counter() - t0
    deformer.solve(moves[0])  # warm-up
    times = []
    for P in moves:
        t = time.perf_counter()
        deformer.solve(P)
        times.append(time.perf_counter() - t)
    return setup, float(np.median(times)), deformer.backend


def time_arap(V, F, handles, moves) -> tuple[float, float]:
    import igl

    data = igl.ARAPData()
    data.max_iter = 10
    t0 = time.perf_counter()
    igl.arap_precomputation(V, F, 3, handles.astype(np.int32), data)
    setup = time.perf_counter() - t0
    U = V.copy()
    times = []
    for P in moves:
        t = time.perf_counter()
        U = igl.arap_solve(P, data, U)
        times.append(time.perf_counter() - t)
    return setup, float(np.median(times))


def main() -> None:
    name = sys.argv[1] if len(sys.argv) > 1 else "rocker-arm.obj"
    V, F = load_bench_mesh(name)
    handles = two_handle_regions(V)
    moves = random_drags(V, handles, DRAGS)
    print(f"mesh {name}: {len(V)} vertices, {len(F)} faces, {len(handles)} handle vertices, "
          f"median of {DRAGS} drags")
    print("| method | setup (factorize / precompute) s | per drag ms |")
    print("|---|---|---|")
    for orth in (False, True):
        setup, drag, backend = time_ours(V, F, handles, moves, orth)
        label = "Deformer.solve" + (" (orthonormalize)" if orth else "")
        print(f"| {label}, {backend} | {setup:.3f} | {drag * 1000:.1f} |", flush=True)
    try:
        setup, drag = time_arap(V, F, handles, moves)
        print(f"| libigl ARAP, 10 iterations | {setup:.3f} | {drag * 1000:.1f} |")
    except ImportError:
        print("| libigl ARAP | not installed (pip install libigl) | |")


if __name__ == "__main__":
    main()
