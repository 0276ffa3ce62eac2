"""Pose pairs for shape-space tests and benchmarks: near-isometric deformations of one mesh
made by the library's own deformation (handles of the Botsch-Sorkine cases, or the two ends
of a mesh's longest axis), and non-isometric companions (smoothed, anisotropically scaled)."""

from __future__ import annotations

import numpy as np

from solver import deform


def rotation(axis: int, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about coordinate axis ``axis``."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def end_regions(V: np.ndarray, fraction: float = 0.05) -> tuple[np.ndarray, np.ndarray, int]:
    """The vertices of ``V`` (n, 3) in the lowest and highest ``fraction`` along its longest
    axis (at least 4 each), and that axis."""
    axis = int(np.argmax(np.ptp(V, axis=0)))
    order = np.argsort(V[:, axis])
    k = max(int(len(V) * fraction), 4)
    return order[:k], order[-k:], axis


def bent_pose(V: np.ndarray, F: np.ndarray, angle: float, *, bend_axis: int | None = None,
              refine: bool | None = None) -> np.ndarray:
    """``V`` (n, 3) bent by ``angle`` radians: one end of its longest axis held, the other
    turned by ``angle`` about an axis across it through the mesh's centre (positions and
    orientation handles), the rest deformed by :func:`solver.deform` (near-isometric)."""
    low, high, axis = end_regions(V)
    across = (axis + 1) % 3 if bend_axis is None else bend_axis
    R = rotation(across, angle)
    pivot = V.mean(axis=0)
    handles = np.concatenate([low, high])
    targets = np.concatenate([V[low], (V[high] - pivot) @ R.T + pivot])
    held = np.isin(F, high).all(axis=1)
    groups = [np.flatnonzero(np.isin(F, low).all(axis=1)), np.flatnonzero(held)]
    rotations = np.stack([np.eye(3), R])
    return deform(V, F, handles, targets, rotation_handles=groups,
                  handle_rotations=rotations, refine=refine).vertices


def case_pose(case, fraction: float) -> np.ndarray:
    """A Botsch-Sorkine case (:mod:`tests.helpers.botsch_sorkine`) deformed by ``fraction``
    of its handle transform (the rotation's angle and the translation scaled)."""
    from scipy.spatial.transform import Rotation

    T = case.transform
    R = Rotation.from_matrix(T[:3, :3]).as_rotvec() * fraction
    R = Rotation.from_rotvec(R).as_matrix()
    P = case.vertices[case.handles]
    targets = P @ R.T + T[:3, 3] * fraction
    return deform(case.vertices, case.faces, case.handles, targets,
                  rotation_handles=[case.handle_faces()], handle_rotations=R[None],
                  roi=case.roi).vertices


def smoothed(V: np.ndarray, F: np.ndarray, steps: int = 10, rate: float = 0.5) -> np.ndarray:
    """``V`` (n, 3) after ``steps`` of uniform Laplacian smoothing (a different shape with
    the same connectivity)."""
    import scipy.sparse as sp

    n = len(V)
    i = np.concatenate([F[:, 0], F[:, 1], F[:, 2], F[:, 1], F[:, 2], F[:, 0]])
    j = np.concatenate([F[:, 1], F[:, 2], F[:, 0], F[:, 0], F[:, 1], F[:, 2]])
    A = sp.csr_array((np.ones(len(i)), (i, j)), shape=(n, n))
    A.data[:] = 1.0
    degree = np.asarray(A.sum(axis=1)).ravel()
    X = V.copy()
    for _ in range(steps):  # a loop over smoothing steps, not mesh elements
        X = X + rate * (A @ X / degree[:, None] - X)
    return X
