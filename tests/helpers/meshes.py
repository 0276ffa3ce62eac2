"""Test meshes: small shared meshes copied to tests/data and procedural ones with known topology."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import trimesh

from tests.helpers import DATA, REPO

if TYPE_CHECKING:
    from solver.mesh.topology import MeshTopology

SHARED = REPO.parent / "shared" / "meshes"
"""The larger shared meshes beside the repository (may be absent)."""


def load(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Read tests/data/<name> with trimesh (not the solver's reader), in file order.

    Returns:
        (vertices (n, 3) float64, faces (m, 3) int64).
    """
    mesh = trimesh.load(DATA / name, process=False)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def icosphere(subdivisions: int = 2, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """trimesh's icosphere: 20 * 4**subdivisions faces.

    Returns:
        (vertices (n, 3) float64, faces (m, 3) int64).
    """
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def grid(nx: int, ny: int, *, width: float = 1.0, height: float = 1.0,
         drop: set[tuple[int, int]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated (nx x ny)-cell grid in the xy plane, counter-clockwise seen from +z.

    Cells in ``drop`` are left out (holes). Unused vertices are removed.
    """
    xs, ys = np.meshgrid(np.linspace(0, width, nx + 1), np.linspace(0, height, ny + 1))
    V = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    idx = np.arange((nx + 1) * (ny + 1)).reshape(ny + 1, nx + 1)
    cells = [(i, j) for j in range(ny) for i in range(nx) if (i, j) not in (drop or set())]
    i, j = np.array(cells).T
    a, b, c, d = idx[j, i], idx[j, i + 1], idx[j + 1, i + 1], idx[j + 1, i]
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    used = np.unique(F)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def bumpy_grid(nx: int = 8, ny: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """An open, curved grid (disk topology) of ``nx`` x ``ny`` cells."""
    V, F = grid(nx, ny, width=1.5, height=1.0)
    V[:, 2] = 0.2 * np.sin(3 * V[:, 0]) * np.cos(4 * V[:, 1])
    return V, F


def bumpy_grid_with_holes() -> tuple[np.ndarray, np.ndarray]:
    """Open surface with three boundary loops (outer + two holes), curved and irregular."""
    drop = {(3, 3), (3, 4), (4, 3), (4, 4), (10, 5), (11, 5), (10, 6)}
    V, F = grid(15, 10, width=1.5, height=1.0, drop=drop)
    rng = np.random.default_rng(3)
    V[:, :2] += rng.uniform(-0.02, 0.02, size=(len(V), 2))
    V[:, 2] = 0.2 * np.sin(3 * V[:, 0]) * np.cos(4 * V[:, 1])
    return V, F


def skinny_grid() -> tuple[np.ndarray, np.ndarray]:
    """Curved strip of very skinny triangles (aspect ratio ~ 200)."""
    V, F = grid(40, 4, width=1.0, height=0.0005 * 4 * 50)
    V[:, 0] *= 10.0
    V[:, 2] = 0.3 * np.sin(V[:, 0])
    return V, F


def torus_grid(nu: int, nv: int, R: float = 2.0, r: float = 0.7,
               flat: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Torus from a periodic nu x nv grid. With ``flat`` the vertices are the planar grid
    (coordinates of one period) -- used only for the connectivity and flat lengths."""
    u, v = np.meshgrid(np.arange(nu) / nu * 2 * np.pi, np.arange(nv) / nv * 2 * np.pi,
                       indexing="ij")
    V = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u),
                  r * np.sin(v)], axis=-1).reshape(-1, 3)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a = idx
    b = np.roll(idx, -1, axis=0)
    c = np.roll(np.roll(idx, -1, axis=0), -1, axis=1)
    d = np.roll(idx, -1, axis=1)
    F = np.concatenate([np.stack([a.ravel(), b.ravel(), c.ravel()], 1),
                        np.stack([a.ravel(), c.ravel(), d.ravel()], 1)])
    if flat:
        V = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    return V, F


def flat_torus_forms(nu: int = 8, nv: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                        np.ndarray]:
    """Forms of a flat torus: periodic grid with unit squares and all angles 0.

    Returns (faces, edges, lengths, angles). Locally integrable everywhere (flat), but the
    translation around each homology generator is a full period, not 0.
    """
    _, F = torus_grid(nu, nv)
    half = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    keys = np.unique(np.sort(half, axis=1), axis=0)
    # Lengths from the periodic grid: axis steps 1, diagonal sqrt(2).
    iu, iv = np.divmod(keys, nv)
    du = np.minimum(np.abs(iu[:, 0] - iu[:, 1]), nu - np.abs(iu[:, 0] - iu[:, 1]))
    dv = np.minimum(np.abs(iv[:, 0] - iv[:, 1]), nv - np.abs(iv[:, 0] - iv[:, 1]))
    lengths = np.sqrt(du**2 + dv**2).astype(np.float64)
    return F, keys, lengths, np.zeros(len(keys))


def voxel_surface(mask: np.ndarray, jitter: float = 0.0,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Closed surface bounding the filled voxels of a 3D boolean mask (outward, CCW).

    The mask must not contain voxels touching only along an edge or at a corner (which
    would make the surface non-manifold).
    """
    padded = np.pad(mask, 1)
    quads = []
    for axis in range(3):
        for sign in (1, -1):
            shifted = np.roll(padded, -sign, axis=axis)
            cells = np.argwhere(padded & ~shifted)
            for cell in cells:
                quads.append(_voxel_quad(cell, axis, sign))
    corners = np.array(quads).reshape(-1, 3)
    V, inverse = np.unique(corners, axis=0, return_inverse=True)
    Q = inverse.reshape(-1, 4)
    F = np.concatenate([Q[:, [0, 1, 2]], Q[:, [0, 2, 3]]])
    V = V.astype(np.float64)
    if jitter:
        V += np.random.default_rng(seed).uniform(-jitter, jitter, size=V.shape)
    return V, F


def _voxel_quad(cell: np.ndarray, axis: int, sign: int) -> np.ndarray:
    """The 4 corners of the face of voxel ``cell`` facing ``sign`` along ``axis``,
    counter-clockwise seen from outside."""
    u, v = [(1, 2), (2, 0), (0, 1)][axis]
    base = cell.astype(float).copy()
    if sign > 0:
        base[axis] += 1
    square = []
    for du, dv in [(0, 0), (1, 0), (1, 1), (0, 1)]:
        p = base.copy()
        p[u] += du
        p[v] += dv
        square.append(p)
    square = np.array(square)
    return square if sign > 0 else square[::-1]


def double_torus(jitter: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Genus-2 closed surface: a voxel plate with two holes, jittered to be generic."""
    mask = np.zeros((7, 4, 2), dtype=bool)
    mask[:, :, :] = True
    mask[1, 1:3, :] = False
    mask[5, 1:3, :] = False
    return voxel_surface(mask, jitter=jitter)


def sphere_cap(subdivisions: int = 3, below: float = -0.6) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere's faces whose centroid is above z = ``below``, vertices renumbered: a
    strongly curved disk (a sphere with a hole at its south pole)."""
    V, F = icosphere(subdivisions)
    keep = V[F].mean(axis=1)[:, 2] > below
    used = np.unique(F[keep])
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    return V[used], remap[F[keep]]


def holed(V: np.ndarray, F: np.ndarray, centres: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """``(V, F)`` without the faces around the vertices ``centres`` (small holes), the
    vertices no face uses dropped and the faces renumbered."""
    keep = F[~np.isin(F, centres).any(axis=1)]
    used = np.unique(keep)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    return V[used], remap[keep]


def side_by_side(*meshes: tuple[np.ndarray, np.ndarray], gap: float = 1.5,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """One multi-part model of ``meshes`` ((V, F) pairs): each scaled to unit size and set
    ``gap`` apart along +x, faces renumbered."""
    vertices, faces, offset, shift = [], [], 0, 0.0
    for V, F in meshes:
        V = (np.asarray(V, dtype=np.float64) - np.min(V, axis=0)) / np.ptp(V, axis=0).max()
        vertices.append(V + np.array([shift, 0.0, 0.0]))
        faces.append(np.asarray(F) + offset)
        offset += len(V)
        shift += gap
    return np.concatenate(vertices), np.concatenate(faces)


def rigid_alignment_error(X: np.ndarray, Y: np.ndarray) -> float:
    """max |R X + t - Y| over vertices after the best rotation + translation (no scaling),
    divided by the bounding-box diagonal of Y."""
    Xc, Yc = X - X.mean(axis=0), Y - Y.mean(axis=0)
    U, _, Vt = np.linalg.svd(Xc.T @ Yc)
    d = np.sign(np.linalg.det(U @ Vt))
    R = U @ np.diag([1.0, 1.0, d]) @ Vt
    diagonal = np.linalg.norm(Y.max(axis=0) - Y.min(axis=0))
    return float(np.abs(Xc @ R - Yc).max() / diagonal)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _separate_interior_edges(topo: MeshTopology, n_faces: int, count: int, seed: int) -> list[int]:
    """Up to ``count`` interior edge ids of ``topo``, no two sharing a face, in a random
    order drawn from ``seed`` (the edges the mesh degraders below split)."""
    rng = np.random.default_rng(seed)
    used = np.zeros(n_faces, dtype=bool)
    chosen = []
    for e in rng.permutation(topo.interior_edges):  # test data: a short loop is fine
        left, right = topo.edge_faces[e]
        if not used[left] and not used[right]:
            used[[left, right]] = True
            chosen.append(e)
            if len(chosen) == count:
                break
    return chosen


def _edge_points(V: np.ndarray, F: np.ndarray, count: int, seed: int, at: float,
                 ) -> tuple[MeshTopology, np.ndarray, np.ndarray, list[int], np.ndarray]:
    """What the edge splitters below start from: the topology of ``F``, float64 and int64
    copies of ``V`` and ``F``, the chosen edges (:func:`_separate_interior_edges`) and the
    points (len(chosen), 3) at ``i + at (j - i)`` on each edge ``[i, j]``."""
    from solver.mesh.topology import build_topology

    topo = build_topology(F, len(V))
    chosen = _separate_interior_edges(topo, len(F), count, seed)
    V = np.array(V, dtype=np.float64)
    F = np.array(F, dtype=np.int64)
    i, j = topo.edges[np.asarray(chosen, dtype=np.int64)].reshape(-1, 2).T
    return topo, V, F, chosen, V[i] + at * (V[j] - V[i])


def with_tiny_edges(V: np.ndarray, F: np.ndarray, count: int, ratio: float = 1e-4,
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A very irregular version of a closed mesh: ``count`` interior edges ``[i, j]`` (no two
    sharing a face) split at ``i + ratio (j - i)``, each into a tiny edge of ``ratio`` times
    its length and two needle faces (the four new faces stay counter-clockwise).

    Returns (vertices (n + count, 3), faces (m + 2 count, 3)). The surface is unchanged, so
    its forms are integrable; only the sampling degenerates (edge-length ratios ~1 / ratio).
    """
    topo, V, F, chosen, points = _edge_points(V, F, count, seed, ratio)
    new_faces = []
    for k, e in enumerate(chosen):
        i, j = topo.edges[e]
        p = len(V) + k
        for t in topo.edge_faces[e]:
            # Rotate the face so that it reads (u, w, tip) with u -> w one of i -> j, j -> i.
            turn = next(r for r in range(3) if {F[t][r], F[t][(r + 1) % 3]} == {i, j})
            u, w, tip = np.roll(F[t], -turn)
            F[t] = (u, p, tip)
            new_faces.append((p, w, tip))
    return (np.concatenate([V, points]),
            np.concatenate([F, np.array(new_faces, dtype=np.int64).reshape(-1, 3)]))


def with_zero_area_faces(V: np.ndarray, F: np.ndarray, count: int, seed: int = 0,
                         at: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A mesh with ``count`` inserted zero-area faces (as T-junction repairs leave them):
    for interior edges ``[i, j]`` (no two sharing a face), a vertex ``p`` on the segment at
    ``i + at (j - i)``, the face right of ``i -> j`` split into two at ``p`` and the
    zero-area face ``(j, i, p)`` (collinear corners) between them and the face left of it.
    The surface is unchanged; the mesh stays manifold and consistently oriented.

    Returns (vertices (n + count, 3), faces (m + 2 count, 3)).
    """
    topo, V, F, chosen, points = _edge_points(V, F, count, seed, at)
    new_faces = []
    for k, e in enumerate(chosen):
        i, j = topo.edges[e]
        p = len(V) + k
        right = topo.edge_faces[e, 1]  # the face with the half-edge j -> i
        turn = next(r for r in range(3) if (F[right][r], F[right][(r + 1) % 3]) == (j, i))
        _, _, b = np.roll(F[right], -turn)
        F[right] = (j, p, b)
        new_faces += [(p, i, b), (j, i, p)]
    return (np.concatenate([V, points]),
            np.concatenate([F, np.array(new_faces, dtype=np.int64).reshape(-1, 3)]))


def with_cap_faces(V: np.ndarray, F: np.ndarray, count: int, height: float = 1e-6,
                   seed: int = 3) -> np.ndarray:
    """Vertices of a mesh with up to ``count`` near-zero-area "cap" faces: for faces
    ``[a, b, c]`` (no two sharing a vertex), ``c`` moved to the midpoint of ``a b`` lifted
    by ``height`` times ``|b - a|`` along the face's normal (a 180° corner; exactly zero
    area would leave the face's normal, so its dihedral angles, undefined). The faces are
    unchanged; the surface around each moved vertex is dented.

    Returns (n, 3) float64 vertices.
    """
    V = np.array(V, dtype=np.float64)
    used: set[int] = set()
    for t in np.random.default_rng(seed).choice(len(F), count, replace=False):
        a, b, c = (int(v) for v in F[t])  # test data: a short loop is fine
        if used & {a, b, c}:
            continue
        normal = np.cross(V[b] - V[a], V[c] - V[a])
        V[c] = 0.5 * (V[a] + V[b]) + height * np.linalg.norm(V[b] - V[a]) * normal / \
            np.linalg.norm(normal)
        used |= {a, b, c}
    return V


def with_noisy_angles(forms, seed: int = 1, sigma: float = 1e-3):
    """A copy of ``forms`` (:class:`solver.Forms`) with N(0, ``sigma``) rad drawn from
    ``default_rng(seed)`` added to the dihedral angles of the interior edges, in edge order
    (boundary angles stay 0): the noisy forms of the tests and of bench/."""
    import solver
    from solver.mesh.topology import build_topology

    inner = build_topology(forms.faces).interior_edges
    angles = np.array(forms.angles, dtype=np.float64)
    angles[inner] += np.random.default_rng(seed).normal(0, sigma, len(inner))
    return solver.Forms(forms.faces, forms.edges, forms.lengths, angles)
