"""Synthetic stand-ins for meshes as people have them (issue 40): non-manifold edges and
vertices, many components, fins folded at pi, closed surfaces of genus 0 and 2, slivers.

Each builder returns ``(vertices (n, 3) float64, faces (m, 3) int64)`` with known geometry,
so a round trip can be checked against the mesh itself after one rigid alignment.
"""

from __future__ import annotations

import numpy as np

from tests.helpers.meshes import (
    double_torus,
    grid,
    icosphere,
    random_rotation,
    torus_grid,
    voxel_surface,
    with_cap_faces,
    with_tiny_edges,
    with_zero_area_faces,
)


def _merge(*parts: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Disjoint union of meshes (vertices renumbered part after part)."""
    vertices, faces, offset = [], [], 0
    for V, F in parts:
        vertices.append(np.asarray(V, dtype=np.float64))
        faces.append(np.asarray(F, dtype=np.int64) + offset)
        offset += len(V)
    return np.concatenate(vertices), np.concatenate(faces)


def _glue(V: np.ndarray, F: np.ndarray, keep: int, drop: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ``drop`` merged into ``keep`` (same position) and removed."""
    F = np.where(drop == F, keep, F)
    F = np.where(drop < F, F - 1, F)
    return np.delete(V, drop, axis=0), F


def box_with_fin() -> tuple[np.ndarray, np.ndarray]:
    """A closed voxel box (jittered) with a two-triangle fin glued along one of its edges:
    that edge has 3 faces."""
    V, F = voxel_surface(np.ones((2, 2, 2), dtype=bool), jitter=0.05, seed=4)
    top = np.flatnonzero(V[:, 2] > 1.5)
    a = top[np.argmin(V[top, 0] + V[top, 1])]
    neighbours = np.unique(F[(a == F).any(axis=1)])
    b = next(int(v) for v in neighbours if v in top and v != a)
    out = np.array([-0.6, -0.4, 0.9])
    c, d = V[b] + out, V[a] + out + [0.1, 0, 0]
    n = len(V)
    return np.vstack([V, c, d]), np.vstack([F, [[a, b, n], [a, n, n + 1]]])


def boxes_sharing_an_edge() -> tuple[np.ndarray, np.ndarray]:
    """Two closed voxel boxes touching along one edge (4 faces on it; its two end vertices
    join two fans each)."""
    mask = np.zeros((2, 2, 1), dtype=bool)
    mask[0, 0, 0] = mask[1, 1, 0] = True
    V, F = voxel_surface(mask)
    rng = np.random.default_rng(7)
    return V + rng.uniform(-0.05, 0.05, V.shape), F


def cones_at_apex() -> tuple[np.ndarray, np.ndarray]:
    """Two closed cones touching at their apex (one vertex, two fans)."""
    sections = 14
    angle = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    rim = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(sections)])
    ring = np.arange(sections)
    nxt = (ring + 1) % sections
    # Cone 1: apex 0 at (0, 0, 2), rim 1..s, base centre s+1; outward normals.
    V1 = np.vstack([[0, 0, 2.0], rim, [0, 0, 0]])
    F1 = np.vstack([np.column_stack([np.zeros(sections, int), ring + 1, nxt + 1]),
                    np.column_stack([np.full(sections, sections + 1), nxt + 1, ring + 1])])
    R = random_rotation(np.random.default_rng(2))
    V2 = (V1 - [0, 0, 2.0]) * [1.3, 0.8, -1.0] @ R.T + [0, 0, 2.0]
    F2 = F1[:, ::-1]
    V, F = _merge((V1, F1), (V2, F2))
    return _glue(V, F, 0, len(V1))


def multi_component() -> tuple[np.ndarray, np.ndarray]:
    """Four parts apart from each other: a sphere, a torus, a box and an open grid."""
    rng = np.random.default_rng(5)
    parts = [icosphere(2), torus_grid(12, 8), voxel_surface(np.ones((1, 2, 1), bool)),
             grid(5, 4)]
    placed = []
    for k, (V, F) in enumerate(parts):
        placed.append((np.asarray(V) @ random_rotation(rng).T + [4.0 * k, 0.5 * k, 0], F))
    return _merge(*placed)


def folded_sheet() -> tuple[np.ndarray, np.ndarray]:
    """A grid folded flat onto itself along a line: the fold's edges have a dihedral angle
    of exactly pi (the two halves lie on each other)."""
    V, F = grid(8, 4, width=2.0, height=1.0)
    V = np.asarray(V, dtype=np.float64).copy()
    fold = 1.0
    right = V[:, 0] > fold + 1e-9
    V[right, 0] = 2 * fold - V[right, 0]
    V[:, 2] = 0.0
    return V, np.asarray(F)


def closed_genus0() -> tuple[np.ndarray, np.ndarray]:
    """An icosphere (closed, genus 0)."""
    return icosphere(2)


def closed_genus2() -> tuple[np.ndarray, np.ndarray]:
    """A jittered voxel plate with two holes (closed, genus 2)."""
    return double_torus(jitter=0.1)


def slivers(seed: int = 0, ratio: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere with edges split near their endpoints: needles and slivers (edge-length
    ratios ~1 / ratio) on an unchanged surface."""
    V, F = icosphere(3)
    return with_tiny_edges(V, F, count=60, ratio=ratio, seed=seed)


def zero_area_inserted() -> tuple[np.ndarray, np.ndarray]:
    """An icosphere with 12 inserted zero-area faces (a vertex on an edge, T-junction
    repairs: :func:`tests.helpers.meshes.with_zero_area_faces`)."""
    V, F = icosphere(3)
    return with_zero_area_faces(V, F, 12, seed=2)


def zero_area_collinear() -> tuple[np.ndarray, np.ndarray]:
    """A torus whose faces keep their vertices but 6 of them have collinear corners (a
    corner moved onto the midpoint of the opposite edge: a dent in the surface)."""
    V, F = torus_grid(24, 12)
    return with_cap_faces(V, F, 6, height=0.0, seed=5), np.asarray(F)


def zero_area_open() -> tuple[np.ndarray, np.ndarray]:
    """An open sheet with 6 inserted zero-area faces and 4 collinear ones (flattened)."""
    V, F = grid(10, 8)
    V = np.asarray(V, dtype=np.float64).copy()
    V[:, 2] = 0.2 * np.sin(V[:, 0]) * np.cos(V[:, 1])
    V, F = with_zero_area_faces(V, F, 6, seed=3, at=0.3)
    return with_cap_faces(V, F, 4, height=0.0, seed=4), F


CASES = {
    "edge-with-3-faces": box_with_fin,
    "edge-with-4-faces": boxes_sharing_an_edge,
    "cones-at-apex": cones_at_apex,
    "multi-component": multi_component,
    "fin-at-pi": folded_sheet,
    "closed-genus-0": closed_genus0,
    "closed-genus-2": closed_genus2,
    "slivers-1e-4": lambda: slivers(0, 1e-4),
    "slivers-1e-6": lambda: slivers(1, 1e-6),
    "zero-area-inserted": zero_area_inserted,
    "zero-area-collinear": zero_area_collinear,
    "zero-area-open": zero_area_open,
}
"""Every case by name."""

HAS_CLOSED_PART = {"edge-with-3-faces", "edge-with-4-faces", "cones-at-apex", "multi-component",
                   "closed-genus-0", "closed-genus-2", "slivers-1e-4", "slivers-1e-6",
                   "zero-area-inserted", "zero-area-collinear"}

ZERO_AREA = {"zero-area-inserted", "zero-area-collinear", "zero-area-open"}
"""Cases with faces of zero area (collinear corners)."""
"""Cases with a closed component (flattened only once closed surfaces can be: issue 41)."""


def diagonal(V: np.ndarray) -> float:
    """The bounding-box diagonal."""
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
