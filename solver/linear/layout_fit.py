"""Vertex positions that best fit rotated face layouts: the start of the refinement.

Given a rotation ``R_t`` per face (e.g. the nearest rotations to the frames of the linear
answer of Eq. 5), each face's layout says where its edges should point: the half-edge
``u -> w`` of face ``t`` should be ``R_t [a_w - a_u; 0]`` with ``a`` the face's 2D corner
positions (:func:`solver.mesh.frames.triangle_layouts`). This module solves the least-squares
problem (the "global step" of a local/global iteration, Sorkine and Alexa 2007)::

    min_x  sum_t sum_(u->w in t) |x_w - x_u - R_t d_uw|^2 / |d_uw|^2
         + sum_v w_v |x_v - p_v|^2 / s^2                     (soft position handles)

with hard position handles eliminated and one vertex pinned in each component that no
handle fixes. Every half-edge weighs its *relative* error, as the refinement's energy does
(:mod:`solver.refine`): a tiny edge is placed as accurately, relative to its length, as a
long one. (Uniform weights leave the 1e-4-long edges of an irregular mesh with relative
errors of 100-500%, from which Gauss-Newton crawls; docs/refinement.md.)

The matrix is a weighted graph Laplacian of order n (three right-hand sides, one per
coordinate): far cheaper than a second factorization of Eq. 5's (n + 3m) system, which the
orthonormalized answer of Sec. 4 needs, and as good a start (measured in
docs/refinement.md). :class:`LayoutFit` factorizes it once for a set of handles; each
:meth:`LayoutFit.solve` back-substitutes.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..linalg import factorize
from ..mesh.topology import MeshTopology


class LayoutFit:
    """Prefactorized least-squares fit of positions to rotated layouts.

    Args:
        topology: the connectivity (n vertices, m faces).
        layouts: (m, 3, 2) float64 2D corner positions of each face, in the units of the
            positions (target edge lengths).
        fixed: (h,) int64 vertices whose positions are given at each :meth:`solve` (hard
            handles, vertices outside a region of interest).
        soft: (p,) int64 vertices pulled towards given positions with ``soft_weights``
            (p,) > 0 (relative to a squared relative edge error; divided by ``s^2``, s the
            mean layout edge length).
        backend: sparse factorization backend (:func:`solver.linalg.factorize`).

    Vertices in components that neither ``fixed`` nor ``soft`` reach get one pinned vertex
    (their first face's first corner), placed at each solve where ``pinned_positions`` says;
    unreferenced vertices are pinned too. ``pinned`` lists them.

    Example::

        >>> import numpy as np, solver
        >>> from solver.mesh.frames import face_edge_lengths, triangle_layouts, layout_frames
        >>> from solver.mesh.topology import build_topology
        >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.3]])
        >>> topo = build_topology(np.array([[0, 1, 2], [2, 1, 3]]))
        >>> forms = solver.fundamental_forms(V, topo.faces)
        >>> layouts = triangle_layouts(face_edge_lengths(topo, forms.lengths))
        >>> fit = LayoutFit(topo, layouts)
        >>> X = fit.solve(layout_frames(V, topo.faces, layouts), pinned_positions=V[fit.pinned])
        >>> bool(np.allclose(X, V))
        True
    """

    def __init__(self, topology: MeshTopology, layouts: np.ndarray,
                 fixed: np.ndarray | None = None, soft: np.ndarray | None = None,
                 soft_weights: np.ndarray | None = None, backend: str = "auto") -> None:
        n, faces = topology.n_vertices, topology.faces
        self.topology = topology
        self.fixed = np.zeros(0, np.int64) if fixed is None else np.asarray(fixed, np.int64)
        self.soft = np.zeros(0, np.int64) if soft is None else np.asarray(soft, np.int64)
        weights = np.zeros(0) if soft_weights is None else np.asarray(soft_weights, float)
        # Half-edges u -> w of every face, their planar target vectors and weights.
        self._tail = faces.ravel()                                   # (3m,) corner c
        self._head = faces[:, [1, 2, 0]].ravel()                     # corner c + 1
        self._planar = (layouts[:, [1, 2, 0]] - layouts).reshape(-1, 2)  # (3m, 2)
        length2 = np.einsum("ij,ij->i", self._planar, self._planar)
        scale2 = float(np.mean(length2)) if len(length2) else 1.0
        self._weights = 1.0 / np.maximum(length2, 1e-24 * scale2)
        self._soft_weights = weights / scale2
        # Components that nothing places: pin a vertex each (and every unreferenced one).
        reached = np.zeros(topology.n_components, dtype=bool)
        reached[topology.vertex_component[np.concatenate([self.fixed, self.soft])]] = True
        comps, first_face = np.unique(topology.face_component, return_index=True)
        self.pinned = np.concatenate([faces[first_face[~reached[comps]], 0],
                                      topology.isolated_vertices]).astype(np.int64)
        given = np.zeros(n, dtype=bool)
        given[self.fixed] = True
        given[self.pinned] = True
        self._free = np.flatnonzero(~given)
        self._given = np.flatnonzero(given)
        laplacian = self._laplacian(n)
        self._coupling = laplacian[self._free][:, self._given]
        self._factor = factorize(laplacian[self._free][:, self._free], backend,
                                 assume_symmetric=True) if len(self._free) else None

    def _laplacian(self, n: int) -> sp.csr_array:
        """(n, n) weighted graph Laplacian of the half-edge rows plus the soft handles."""
        u, w, k = self._tail, self._head, self._weights
        rows = np.concatenate([u, w, u, w, self.soft])
        cols = np.concatenate([u, w, w, u, self.soft])
        vals = np.concatenate([k, k, -k, -k, self._soft_weights])
        return sp.csr_array(sp.coo_array((vals, (rows, cols)), shape=(n, n)))

    def solve(self, rotations: np.ndarray, fixed_positions: np.ndarray | None = None,
              soft_positions: np.ndarray | None = None,
              pinned_positions: np.ndarray | None = None) -> np.ndarray:
        """Positions (n, 3) float64 for face rotations (m, 3, 3) (columns b1, b2, b3: the
        layout's x and y axes and the normal), hard positions (h, 3) of ``fixed``, soft
        targets (p, 3) of ``soft`` and positions (len(pinned), 3) of ``pinned`` (default:
        zeros)."""
        n = self.topology.n_vertices
        m = len(rotations)
        axes = np.repeat(rotations[:, :, :2], 3, axis=0) if m else np.zeros((0, 3, 2))
        target = np.einsum("hkc,hc->hk", axes, self._planar)         # (3m, 3)
        flux = self._weights[:, None] * target
        rhs = np.stack([np.bincount(self._head, flux[:, k], n) -
                        np.bincount(self._tail, flux[:, k], n) for k in range(3)], axis=1)
        if len(self.soft):
            rhs[self.soft] += self._soft_weights[:, None] * soft_positions
        X = np.zeros((n, 3))
        if len(self.fixed):
            X[self.fixed] = fixed_positions
        if len(self.pinned) and pinned_positions is not None:
            X[self.pinned] = pinned_positions
        if self._factor is not None:
            X[self._free] = self._factor.solve(rhs[self._free] -
                                               self._coupling @ X[self._given])
        return X
