"""Meshes with vertices joined by zero-length edges (issue 40, :mod:`solver.mesh.weld`):
capsule-like latitude-longitude grids whose poles are repeated once per longitude (as
trimesh's models/capsule.obj has them), a duplicated corner, a face written ``(a, a, b)``,
and shared meshes with random edges split exactly at (or within 1e-15 of) an endpoint.

Each builder returns ``(vertices (n, 3) float64, faces (m, 3) int64, welded, dropped)``:
how many vertices the rule welds and faces it drops, counted from the construction.
"""

from __future__ import annotations

import numpy as np

from tests.helpers.meshes import SHARED, icosphere, with_tiny_edges

Welded = tuple[np.ndarray, np.ndarray, int, int]


def latlong(radius: np.ndarray, height: np.ndarray, columns: int) -> Welded:
    """A surface of revolution sampled on a (rows, columns + 1) grid: the seam column is
    repeated (coincident, joined by no edge: a split seam, zipped by the weld: its rows - 2
    copies off the poles are welded) and the first and last rows have radius 0 (a pole
    repeated once per column: each pole quad has a face with two corners at one
    position)."""
    rows = len(radius)
    angle = np.linspace(0.0, 2 * np.pi, columns + 1)
    angle[-1] = 0.0  # the seam copy at exactly the first column's position
    V = np.stack([radius[:, None] * np.cos(angle), radius[:, None] * np.sin(angle),
                  np.broadcast_to(height[:, None], (rows, columns + 1))], axis=-1)
    V = V.reshape(-1, 3).copy()
    index = np.arange(rows * (columns + 1)).reshape(rows, columns + 1)
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    F = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                        np.stack([b, c, d], -1).reshape(-1, 3)])
    F = F[:, ::-1] if height[0] > height[-1] else F  # outward normals
    return V, F, 2 * columns + rows - 2, 2 * columns


def latlong_sphere(rows: int = 10, columns: int = 16) -> Welded:
    """A unit sphere as a latitude-longitude grid (poles repeated per column)."""
    polar = np.linspace(np.pi, 0.0, rows + 1)
    radius = np.sin(polar)
    radius[[0, -1]] = 0.0
    return latlong(radius, np.cos(polar), columns)


def latlong_capsule(rows: int = 6, columns: int = 20, length: float = 2.0) -> Welded:
    """A capsule (a cylinder between two hemispheres) as a latitude-longitude grid."""
    polar = np.linspace(np.pi, np.pi / 2, rows + 1)
    radius = np.concatenate([np.sin(polar), np.sin(polar[::-1])])
    height = np.concatenate([np.cos(polar), np.cos(polar[::-1]) + length])
    radius[[0, -1]] = 0.0
    return latlong(radius, height, columns)


def duplicated_corner() -> Welded:
    """An icosphere with one edge split exactly at its endpoint: the new vertex sits on
    that endpoint, its two faces there have two corners at one position."""
    V, F = icosphere(2)
    V, F = with_tiny_edges(V, F, count=1, ratio=0.0, seed=3)
    return V, F, 1, 2


def repeated_index_face() -> Welded:
    """An icosphere with an extra face written ``(a, a, b)``."""
    V, F = icosphere(2)
    return V, np.vstack([F, [[7, 7, 12]]]), 0, 1


def shared_with_welded_pairs(name: str, count: int, seed: int, ratio: float = 0.0
                             ) -> Welded:
    """A shared mesh (``../shared/meshes``) with ``count`` random edges split at ``ratio``
    of their length from an endpoint (0: exactly on it; 1e-15: within the weld tolerance)."""
    from solver.mesh.io import load_mesh_file

    V, F = load_mesh_file(SHARED / name)
    V, F = with_tiny_edges(np.asarray(V), np.asarray(F), count=count, ratio=ratio, seed=seed)
    return V, F, count, 2 * count


CASES = {
    "latlong-sphere": latlong_sphere,
    "latlong-capsule": latlong_capsule,
    "duplicated-corner": duplicated_corner,
    "repeated-index-face": repeated_index_face,
    "bunny-welded-pairs": lambda: shared_with_welded_pairs("bunny.off", 40, 1),
    "torus-near-pairs": lambda: shared_with_welded_pairs("torus.off", 25, 2, ratio=1e-15),
    "cactus-welded-pairs": lambda: shared_with_welded_pairs("cactus.off", 30, 3),
}
"""Every case by name."""
