"""Per-drag deformation latency against libigl's ARAP, side by side on a ~20K-face mesh.

Ours: `solver.Deformer` factorizes once (setup), then each drag is `deformer.solve`
(back-substitution only; with orthonormalize, two back-substitutions and a batched polar
projection). libigl: `igl.arap_precomputation` once, then `igl.arap_solve` with 10
iterations per drag (the usual interactive setting). Whole mesh as ROI, the same handle
vertices for both, 30 drags of random handle displacements.

    pip install libigl      # bench-only extra: pip install -e ".[bench]"
    python bench/deform_speed.py [mesh]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from solver import Deformer  # noqa: E402

SHARED = ROOT.parent / "shared" / "meshes"
DRAGS = 30


def handles_for(V: np.ndarray) -> np.ndarray:
    """Two handle regions: the 2% of vertices lowest and highest along the longest axis."""
    axis = int(np.argmax(np.ptp(V, axis=0)))
    order = np.argsort(V[:, axis])
    k = max(len(V) // 50, 4)
    return np.concatenate([order[:k], order[-k:]])


def drags(V: np.ndarray, handles: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    scale = 0.1 * np.linalg.norm(np.ptp(V, axis=0))
    top = len(handles) // 2
    out = []
    for _ in range(DRAGS):
        P = V[handles].copy()
        P[top:] += rng.normal(scale=scale, size=3)
        out.append(P)
    return out


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
    mesh = trimesh.load(SHARED / name, process=False)
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    handles = handles_for(V)
    moves = drags(V, handles)
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
