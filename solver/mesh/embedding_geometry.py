"""An embedding's edge vectors, hinge (dihedral) angles and signed areas, with gradients.

What the refinement's residuals (:mod:`solver.refine.form_energy`,
:mod:`solver.refine.refined_energy`)
measure of positions ``X`` (n, dim): vectorized over all edges, hinges or faces at once, on
axis-first coordinates (:func:`corner_coordinates`).
"""

from __future__ import annotations

import numpy as np

from .topology import MeshTopology


def hinges(topology: MeshTopology) -> tuple[np.ndarray, np.ndarray]:
    """Interior edges and their hinge vertices.

    Returns ``(edges (k,) int64, (k, 4) int64 [i, j, a, b])``: edge ``[i, j]`` (i < j), ``a``
    the tip of the face left of ``i -> j`` and ``b`` the tip of the other face.
    """
    inner = topology.interior_edges
    flat = topology.faces.ravel()
    h_left, h_right = topology.edge_halfedges[inner, 0], topology.edge_halfedges[inner, 1]
    tip = lambda h: flat[3 * (h // 3) + (h % 3 + 2) % 3]  # noqa: E731 - corner opposite h
    i, j = topology.edges[inner, 0], topology.edges[inner, 1]
    return inner, np.stack([i, j, tip(h_left), tip(h_right)], axis=1)


def corner_coordinates(X: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Coordinates (dim, q, k) of the vertices ``index`` (k, q) of ``X`` (n, dim).

    One gather, axis first: every ``[c, slot]`` row is contiguous, so the component-wise
    arithmetic of :func:`hinge_angles` runs on contiguous vectors (about 3x faster than
    (k, 3) rows with ``np.cross`` and ``einsum``; ``docs/refinement.md``).
    """
    k, q = index.shape
    flat = np.take(np.ascontiguousarray(X.T), index.T.ravel(), axis=1)
    return flat.reshape(X.shape[1], q, k)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products (3, k) of axis-first vectors ``a``, ``b`` (3, k)."""
    out = np.empty_like(a)
    np.multiply(a[1], b[2], out=out[0])
    out[0] -= a[2] * b[1]
    np.multiply(a[2], b[0], out=out[1])
    out[1] -= a[0] * b[2]
    np.multiply(a[0], b[1], out=out[2])
    out[2] -= a[1] * b[0]
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products (k,) of axis-first vectors ``a``, ``b`` (3, k)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def hinge_angles(X: np.ndarray, hinge: np.ndarray, floor: float = 0.0,
                 gradients: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed dihedral angles (k,) of hinges (k, 4) of ``X`` (n, 3), and their gradients.

    The angle is that of :func:`solver.mesh.forms.dihedral_angles`. Gradients (k, 4, 3) with
    respect to ``[x_i, x_j, x_a, x_b]`` follow Bridson et al. 2003 (translation invariant:
    they sum to 0); ``floor`` bounds ``|N|^2`` (twice the face area, squared) from below so
    collapsed faces give large but finite gradients.
    """
    P = corner_coordinates(X, hinge)
    xi, xj, xa, xb = P[:, 0], P[:, 1], P[:, 2], P[:, 3]
    e, ea, eb = xj - xi, xa - xi, xb - xj
    elen = np.sqrt(_dot(e, e))
    safe = np.where(elen > 0, elen, 1.0)
    n_left = _cross(e, ea)
    n_right = _cross(eb, e)
    sin = _dot(_cross(n_left, n_right), e) / safe
    theta = np.arctan2(sin, _dot(n_left, n_right))
    if not gradients:
        return theta, None
    u_left = n_left / np.maximum(_dot(n_left, n_left), floor)
    u_right = n_right / np.maximum(_dot(n_right, n_right), floor)
    along_a = _dot(ea, e) / safe  # (x_a - x_i) . e / |e|
    along_b = _dot(eb, e) / safe  # (x_b - x_j) . e / |e|
    G = np.empty((4, 3, len(theta)))
    np.multiply(safe - along_a, u_left, out=G[0])    # -(x_a - x_j).e/|e| u_left ...
    G[0] -= along_b * u_right                       # ... - (x_b - x_j).e/|e| u_right
    np.multiply(along_a, u_left, out=G[1])           # (x_a - x_i).e/|e| u_left ...
    G[1] += (along_b + safe) * u_right              # ... + (x_b - x_i).e/|e| u_right
    np.multiply(-safe, u_left, out=G[2])
    np.multiply(-safe, u_right, out=G[3])
    return theta, G.transpose(2, 0, 1).copy()


def edge_vectors(X: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-first edge vectors (dim, E) ``x_j - x_i`` of edges (E, 2) of ``X`` (n, dim),
    and their lengths (E,)."""
    P = corner_coordinates(X, edges)
    d = P[:, 1] - P[:, 0]
    return d, np.sqrt(np.einsum("ij,ij->j", d, d))


def signed_areas(X: np.ndarray, faces: np.ndarray, gradients: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed areas (m,) of planar faces of ``X`` (n, 2), and gradients (m, 3, 2)."""
    P = corner_coordinates(X, faces)                  # (2, 3, m)
    u, v = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    area = 0.5 * (u[0] * v[1] - u[1] * v[0])
    if not gradients:
        return area, None
    G = np.empty((len(area), 3, 2))
    for corner, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):  # d(A)/d(corner) = perp/2
        opposite = 0.5 * (P[:, a] - P[:, b])
        G[:, corner, 0], G[:, corner, 1] = opposite[1], -opposite[0]
    return area, G
