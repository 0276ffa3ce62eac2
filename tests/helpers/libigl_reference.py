"""libigl's ARAP as the independent reference for deformation and flattening quality.

Shared by tests/solver/test_refine.py and bench/refinement.py, which compare the refined
answers with it in the same run. ``import igl`` happens inside the functions, so callers can
skip where libigl is not installed.
"""

from __future__ import annotations

import numpy as np


def arap_deformation(case, iterations: int = 200) -> np.ndarray:
    """libigl ARAP (spokes and rims) of a Botsch-Sorkine case: fixed region and handles as
    constraints, handles at their targets, ``iterations`` local/global steps from the rest
    shape with the handles moved. Returns (n, 3) float64."""
    import igl

    data = igl.ARAPData()
    data.max_iter = iterations
    b = np.concatenate([case.fixed, case.handles]).astype(np.int64)
    igl.arap_precomputation(case.vertices, case.faces, 3, b, data)
    start = case.vertices.copy()
    start[case.handles] = case.handle_targets()
    bc = np.concatenate([case.vertices[case.fixed], case.handle_targets()])
    return igl.arap_solve(bc, data, start)


def arap_parameterization(V: np.ndarray, F: np.ndarray, iterations: int = 200) -> np.ndarray:
    """libigl's ARAP parameterization (tutorial 503): harmonic start with the boundary loop on
    a circle, one boundary vertex pinned (libigl refuses an empty constraint set), then
    ``iterations`` local/global steps. Returns (n, 2) float64."""
    import igl

    boundary = igl.boundary_loop(F)
    start = igl.harmonic(V, F, boundary, igl.map_vertices_to_circle(V, boundary), 1)
    data = igl.ARAPData()
    data.max_iter = iterations
    pin = np.array([int(boundary[0])])
    igl.arap_precomputation(V, F, 2, pin, data)
    return igl.arap_solve(start[pin], data, start)


def flipped_faces(uv: np.ndarray, F: np.ndarray) -> int:
    """Faces whose orientation in ``uv`` (n, 2) differs from the majority's."""
    e1, e2 = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    return min(int((area < 0).sum()), int((area > 0).sum()))
