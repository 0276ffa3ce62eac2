"""Assembly of the immersion energy of Eq. (5) (solved by :mod:`solver.linear.constrained`).

Unknowns, per coordinate k in {x, y, z}: the vertex coordinates ``x[:, k]`` (n) and row k of
every face frame ``f_t[k, :]`` (3 m), stacked as ``u = [x_k ; f_0[k, :] ; f_1[k, :] ; ...]``.
Both terms of Eq. (5) are row-wise in ``f`` -- ``||f_j - f_i R_ij||_F^2`` sums the squared rows
and ``x_n - x_m - f_T (a1, a2, 0)`` couples coordinate k of x with row k of f_T only -- so the
3 |V| + 9 |F| system splits into three identical systems of size |V| + 3 |F| with one
shared matrix ``K = A^T W A`` and three right-hand sides. ``K`` is factorized once.

Rows of ``A`` (per coordinate):
* edge rows (Eq. 3), one per half-edge h = (m -> n) of face T:
  ``x_n - x_m - a^1 f_T[k, 0] - a^2 f_T[k, 1]`` with weight ``w_{e,T}``;
* frame rows (Eq. 2), three per interior edge (L, R), one per frame column c:
  ``f_R[k, c] - sum_d f_L[k, d] R_LR[d, c]`` with weight ``frame_weight / w_e``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.sparse as sp

from ..mesh.frames import (
    edge_coefficients,
    face_edge_lengths,
    transition_angles,
    transition_quaternions,
    transition_rotations,
    triangle_areas,
    triangle_layouts,
)
from ..mesh.topology import MeshTopology
from .constrained import ConstrainedSystem as ConstrainedSystem  # its home; re-exported

Weighting = Literal["uniform", "cotan", "cotan_clamped"]
WEIGHTINGS: tuple[str, ...] = ("uniform", "cotan", "cotan_clamped")
"""The weightings of Eq. (5) :func:`energy_weights` knows."""
CLAMP_RANGE = (0.05, 5.0)
"""Bounds of the half-cotangent ``w_{e,T}`` under ``"cotan_clamped"``."""


@dataclass
class EnergyTerms:
    """Everything Eq. (5) needs, derived from the forms (no embedding required).

    Attributes:
        topology: the mesh connectivity.
        layouts: (m, 3, 2) 2D corner positions per face.
        coefficients: (m, 3, 2) ``a`` of each half-edge in its face's frame.
        interior_edges: (k,) int64 edges with two faces.
        transition: (k, 3) angles (theta_L, phi, theta_R) of their transition rotations.
        edge_weights: (m, 3) weight of each half-edge row.
        frame_weights: (k,) weight of each interior edge's frame rows (before frame_weight).
        rotations: (k, 3, 3) transition rotations ``R_LR`` of those edges (computed on first
            use: the tree integration needs those of its tree's edges only).
        quaternions: (k, 4) the same rotations as unit quaternions (on first use).
    """

    topology: MeshTopology
    layouts: np.ndarray
    coefficients: np.ndarray
    interior_edges: np.ndarray
    transition: np.ndarray
    edge_weights: np.ndarray
    frame_weights: np.ndarray

    @functools.cached_property
    def rotations(self) -> np.ndarray:
        """(k, 3, 3) float64 :func:`solver.mesh.frames.transition_rotations`."""
        return transition_rotations(self.transition)

    @functools.cached_property
    def quaternions(self) -> np.ndarray:
        """(k, 4) float64 :func:`solver.mesh.frames.transition_quaternions`."""
        return transition_quaternions(self.transition)

    @property
    def n_unknowns(self) -> int:
        """Unknowns per coordinate: n + 3 m."""
        return self.topology.n_vertices + 3 * self.topology.n_faces


COTANGENT_AREA_FLOOR = 1e-12
"""Smallest area of a face, relative to its longest edge squared, in its cotangent weights
(:func:`half_cotangents`): a zero-area face gets weights of ~1e12, not infinities."""


def half_cotangents(face_lengths: np.ndarray) -> np.ndarray:
    """The per-face cotangent weight of each half-edge.

    Args:
        face_lengths: (m, 3) float64 (:func:`solver.mesh.frames.face_edge_lengths`).

    Returns:
        (m, 3) float64 ``cot(angle opposite half-edge k) / 2``.

    Example:
        The 3-4-5 triangle: the right angle faces the hypotenuse (half-edge 2).

        >>> import numpy as np
        >>> from solver.linear.system import half_cotangents
        >>> half_cotangents(np.array([[3.0, 4.0, 5.0]])).round(12).tolist()
        [[0.666666666667, 0.375, 0.0]]
    """
    l0, l1, l2 = face_lengths.T                     # opposite corners 2, 0, 1
    four_area = 4.0 * triangle_areas(face_lengths)
    # A zero-area face (collinear corners, issue 40) has cotangents of +-infinity: its area
    # is floored at COTANGENT_AREA_FLOOR of its longest edge squared (finite, huge weights
    # that the callers' clamps bound).
    longest = face_lengths.max(axis=1)
    four_area = np.maximum(four_area, 4.0 * COTANGENT_AREA_FLOOR * longest**2)
    four_area = np.where(four_area > 0, four_area, np.finfo(float).tiny)
    cot = np.stack([(l1**2 + l2**2 - l0**2), (l2**2 + l0**2 - l1**2),
                    (l0**2 + l1**2 - l2**2)], axis=1) / four_area[:, None]
    return 0.5 * cot


def energy_weights(topology: MeshTopology, face_lengths: np.ndarray,
                   interior_edges: np.ndarray, weighting: Weighting,
                   cotan_floor: float) -> tuple[np.ndarray, np.ndarray]:
    """The weights of the two terms of Eq. (5).

    * ``"cotan"`` -- the paper literally: ``w_{e,T}`` = half cotangent (floored at
      ``cotan_floor``), E_f weighted by ``1 / w_e`` with ``w_e`` the edge's cotangent weight
      floored at ``cotan_floor``. Ill-conditioned on meshes with obtuse triangles.
    * ``"cotan_clamped"`` -- the same Hodge-star weights with ``w_{e,T}`` clamped to
      :data:`CLAMP_RANGE` so that ``1 / w_e`` stays bounded.
    * ``"uniform"`` -- all weights 1 (the default: exact and well-conditioned).

    Args:
        topology: the mesh's connectivity.
        face_lengths: (m, 3) float64.
        interior_edges: (k,) int64.
        weighting: one of :data:`WEIGHTINGS`.
        cotan_floor: lower bound of the cotangent weights under ``"cotan"``.

    Returns:
        ``(edge_weights, frame_weights)``: (m, 3) float64 per half-edge of E_x and (k,)
        float64 per interior edge of E_f.

    Raises:
        ValueError: an unknown weighting.
    """
    m = topology.n_faces
    if weighting == "uniform":
        return np.ones((m, 3)), np.ones(len(interior_edges))
    half_cot = half_cotangents(face_lengths)
    if weighting == "cotan":
        w_half = np.maximum(half_cot, cotan_floor)
        w_edge_raw = np.bincount(topology.halfedge_edge, weights=half_cot.ravel(),
                                 minlength=topology.n_edges)
        w_edge = np.maximum(w_edge_raw, cotan_floor)
    elif weighting == "cotan_clamped":
        w_half = np.clip(half_cot, *CLAMP_RANGE)
        w_edge = np.bincount(topology.halfedge_edge, weights=w_half.ravel(),
                             minlength=topology.n_edges)
    else:
        raise ValueError(f"unknown weighting {weighting!r}; expected one of {WEIGHTINGS}")
    return w_half, 1.0 / w_edge[interior_edges]


def energy_terms(topology: MeshTopology, lengths: np.ndarray, angles: np.ndarray, *,
                 weighting: Weighting = "uniform", cotan_floor: float = 1e-11,
                 layout_angles: np.ndarray | None = None, check: bool = True) -> EnergyTerms:
    """Layouts, edge coefficients, transition rotations and weights from the forms.

    Args:
        topology: the mesh's connectivity.
        lengths: (E,) float64 edge lengths.
        angles: (E,) float64 dihedral angles.
        weighting: see :func:`energy_weights`.
        cotan_floor: see :func:`energy_weights`.
        layout_angles: optional (m,) float64 rotation of each face's 2D frame.
        check: False lays faces that violate the triangle inequality out flat instead of
            raising (used by the integrability report, which lists them).

    Returns:
        The :class:`EnergyTerms`.

    Raises:
        TriangleInequalityError: with ``check``, naming the first impossible face.
    """
    face_lengths = face_edge_lengths(topology, lengths)
    layouts = triangle_layouts(face_lengths, layout_angles, check=check)
    coefficients = edge_coefficients(layouts)
    inner, transition = transition_angles(topology, coefficients, angles)
    w_edge, w_frame = energy_weights(topology, face_lengths, inner, weighting, cotan_floor)
    return EnergyTerms(topology=topology, layouts=layouts, coefficients=coefficients,
                       interior_edges=inner, transition=transition, edge_weights=w_edge,
                       frame_weights=w_frame)


def least_squares_rows(terms: EnergyTerms, frame_weight: float) -> tuple[sp.csr_matrix,
                                                                          np.ndarray,
                                                                          np.ndarray]:
    """The least-squares rows of Eq. (5), one coordinate's worth.

    The energy of one coordinate is ``sum(weights * (A @ u)**2)`` (Eq. 5 without the 1/2).

    Args:
        terms: the forms' :class:`EnergyTerms`.
        frame_weight: the weight of E_f relative to E_x.

    Returns:
        ``(A, weights, kind)``: the (rows, N) CSR residual operator, (rows,) float64 row
        weights and (rows,) int8 row kind (0 edge, 1 frame).
    """
    topo = terms.topology
    n, m = topo.n_vertices, topo.n_faces
    H = 3 * m
    k = len(terms.interior_edges)
    # Every row has exactly four distinct columns: the CSR arrays are written in place, row
    # by row (no COO triplets, no temporaries of the whole matrix, no sort).
    n_rows, n_cols = H + 3 * k, n + 3 * m
    index = np.int32 if max(n_cols, 4 * n_rows + 1) < np.iinfo(np.int32).max else np.int64
    cols = np.empty((n_rows, 4), dtype=index)
    vals = np.empty((n_rows, 4))
    # Edge rows, one per half-edge h of face T: x_dest - x_origin - a1 f_T[0] - a2 f_T[1].
    cols[:H, 0], cols[:H, 1] = topo.halfedge_dest, topo.halfedge_origin
    cols[:H, 2] = n + 3 * (np.arange(H, dtype=index) // 3)    # column of f_T[k, 0]
    cols[:H, 3] = cols[:H, 2] + 1
    vals[:H, 0], vals[:H, 1] = 1.0, -1.0
    vals[:H, 2:] = -terms.coefficients.reshape(H, 2)
    # Frame rows (q, c): f_R[c] - sum_d f_L[d] R[d, c].
    left, right = topo.edge_faces[terms.interior_edges].T
    c = np.arange(3, dtype=index)
    frame_cols = cols[H:].reshape(k, 3, 4)
    frame_cols[:, :, 0] = (n + 3 * right).astype(index)[:, None] + c[None, :]
    frame_cols[:, :, 1:] = (n + 3 * left).astype(index)[:, None, None] + c[None, None, :]
    frame_vals = vals[H:].reshape(k, 3, 4)
    frame_vals[:, :, 0] = 1.0
    frame_vals[:, :, 1:] = np.swapaxes(terms.rotations, 1, 2)
    np.negative(frame_vals[:, :, 1:], out=frame_vals[:, :, 1:])
    cols, vals = cols.reshape(-1), vals.reshape(-1)
    indptr = np.arange(0, 4 * n_rows + 1, 4, dtype=index)
    A = sp.csr_matrix((vals, cols, indptr), shape=(n_rows, n_cols))
    A.sort_indices()
    weights = np.concatenate([terms.edge_weights.ravel(),
                              frame_weight * np.repeat(terms.frame_weights, 3)])
    kind = np.concatenate([np.zeros(H, dtype=np.int8), np.ones(3 * k, dtype=np.int8)])
    return A, weights, kind


def unknown_groups(n_vertices: int, n_faces: int) -> np.ndarray:
    """The ordering hint of :func:`solver.linalg.factorize` for this system's unknowns.

    Args:
        n_vertices: n.
        n_faces: m.

    Returns:
        (n + 3 m,) int64: one group per vertex and one per face (its three frame unknowns
        couple with the same others).

    Example:
        >>> from solver.linear.system import unknown_groups
        >>> unknown_groups(2, 2).tolist()
        [0, 1, 2, 2, 2, 3, 3, 3]
    """
    return np.concatenate([np.arange(n_vertices),
                           n_vertices + np.repeat(np.arange(n_faces), 3)])


def near_null_space(n_vertices: int, immersion: np.ndarray) -> np.ndarray:
    """The near-null space of ``K`` that the multigrid preconditioner keeps exact.

    Per coordinate, Eq. 5's energy vanishes (exact forms) or nearly (noisy ones) on the
    translation and on each coordinate of an immersion of the forms with its frames: for
    exact forms these four span the kernel of ``K`` per connected component.

    Args:
        n_vertices: n.
        immersion: (N, 3) float64 unknowns of an immersion of the forms (e.g. integrated
            along spanning trees, :meth:`solver.immersion.ImmersionProblem.tree_unknowns`).

    Returns:
        (N, 4) float64: the translation (1 on the positions, 0 on the frames) and the three
        columns of ``immersion``.

    Example:
        >>> import numpy as np
        >>> from solver.linear.system import near_null_space
        >>> near_null_space(1, np.arange(12.0).reshape(4, 3))[:, 0].tolist()
        [1.0, 0.0, 0.0, 0.0]
    """
    B = np.empty((immersion.shape[0], 4))
    B[:, 0] = 0.0
    B[:n_vertices, 0] = 1.0
    B[:, 1:] = immersion
    return B


def frame_columns(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """Unknown indices of the frame rows of some faces.

    Args:
        n_vertices: n.
        faces: (k,) int64 face indices.

    Returns:
        (k, 3) int64 unknowns ``f_t[k, 0..2]`` of each face.
    """
    return n_vertices + 3 * np.asarray(faces)[:, None] + np.arange(3)[None, :]


@dataclass
class LinearConstraints:
    """Constraints in unknown space: hard values are eliminated, soft ones are penalties.

    Attributes:
        hard_columns: (h,) int64 unknowns fixed exactly.
        hard_values: (h, 3) float64 their values, one column per coordinate.
        soft_columns: (s,) int64 unknowns pulled towards soft_values with soft_weights.
        soft_values: (s, 3) float64.
        soft_weights: (s,) float64 > 0.
    """

    hard_columns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    hard_values: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    soft_columns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    soft_values: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    soft_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def extended(self, other: LinearConstraints) -> LinearConstraints:
        """Union of two constraint sets (``other`` appended)."""
        return LinearConstraints(
            np.concatenate([self.hard_columns, other.hard_columns]),
            np.concatenate([self.hard_values, other.hard_values]),
            np.concatenate([self.soft_columns, other.soft_columns]),
            np.concatenate([self.soft_values, other.soft_values]),
            np.concatenate([self.soft_weights, other.soft_weights]))


def normal_matrix(A: sp.csr_matrix, weights: np.ndarray) -> sp.csc_matrix:
    """The normal matrix of the least-squares rows.

    Args:
        A: (rows, N) sparse residual operator.
        weights: (rows,) float64 row weights.

    Returns:
        (N, N) CSC ``K = A^T diag(weights) A`` (symmetric positive semi-definite; sorted
        indices).

    The product is formed as ``(W A)^T`` in CSR (one transposed copy of the rows) times
    ``A``; K's CSR arrays are its CSC arrays (K is symmetric, to rounding). scipy's ``A.T @
    diags(w) @ A`` held a weighted copy of A, a CSC copy of it and a CSC copy of K besides:
    at 100K faces 139 against 101 MB of peak above the rows (a scratch tracemalloc probe,
    not a bench/ command), the linear
    answer's memory peak at 1.6M faces.
    """
    A = sp.csr_matrix(A)
    weighted = sp.csr_matrix((A.data * np.repeat(weights, np.diff(A.indptr)), A.indices,
                              A.indptr), shape=A.shape)
    transposed = weighted.T.tocsr()  # (N, rows): A^T W
    del weighted
    K = transposed @ A
    del transposed
    K = sp.csc_matrix((K.data, K.indices, K.indptr), shape=K.shape, copy=False)
    K.sort_indices()
    return K


def energies(A: sp.csr_matrix, weights: np.ndarray, kind: np.ndarray,
             u: np.ndarray, residual: np.ndarray | None = None) -> dict[str, float]:
    """The edge and frame parts of Eq. (5), summed over coordinates.

    Args:
        A: (rows, N) sparse residual operator.
        weights: (rows,) float64 row weights.
        kind: (rows,) int8 row kind (0 edge, 1 frame).
        u: (N, 3) float64 unknowns.
        residual: optional (rows, 3) ``A @ u`` when the caller has it already.

    Returns:
        ``{"edge": E_x, "frame": w E_f}`` floats.
    """
    r = A @ u if residual is None else residual
    r2 = np.square(r[:, 0])                   # column by column: no (rows, 3) temporaries
    for c in range(1, r.shape[1]):
        r2 += np.square(r[:, c])
    r2 *= weights
    return {"edge": float(r2[kind == 0].sum()), "frame": float(r2[kind == 1].sum())}


RESIDUAL_CHUNK = 1 << 16
"""Faces (or interior edges) per block of :func:`residual_summary`: its temporaries stay a
few MB (in cache, and reused by the allocator instead of fresh pages per pass)."""


def residual_summary(terms: EnergyTerms, frame_weight: float, u: np.ndarray,
                     frame_rows: np.ndarray | None = None,
                     chunk: int = RESIDUAL_CHUNK) -> tuple[float, dict[str, float]]:
    """The largest weighted residual row and the energies of Eq. (5) at ``u``, from the
    terms directly (no residual operator ``A``: the tree integration's answer needs only
    these two numbers).

    Row for row the same as ``max_weighted_residual(weights, A @ u)`` and ``energies(A,
    weights, kind, u)`` of :func:`least_squares_rows` (equal to rounding), computed in blocks
    of ``chunk`` faces or interior edges.

    Args:
        terms: the forms' :class:`EnergyTerms`.
        frame_weight: the weight of E_f relative to E_x.
        u: (N, 3) float64 unknowns.
        frame_rows: optional (q,) int64 positions in ``terms.interior_edges`` of the edges
            whose frame rows are evaluated (default all); the caller leaves out rows that
            vanish by construction (the frames of a tree integration satisfy Eq. 2 on its
            tree's edges up to one rounding of the product).
        chunk: block size.

    Returns:
        ``(max |sqrt(w) r|, {"edge": E_x, "frame": w E_f})``.

    Example:
        >>> import numpy as np
        >>> from solver import fundamental_forms
        >>> from solver.linear.system import energy_terms, least_squares_rows, residual_summary
        >>> from solver.mesh.topology import build_topology
        >>> corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> topology = build_topology([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> forms = fundamental_forms(corners, topology.faces)
        >>> terms = energy_terms(topology, forms.lengths, forms.angles, weighting="cotan")
        >>> u = np.random.default_rng(0).normal(size=(terms.n_unknowns, 3))
        >>> A, w, kind = least_squares_rows(terms, 2.0)
        >>> worst, energy = residual_summary(terms, 2.0, u, chunk=1)
        >>> bool(np.isclose(worst, max_weighted_residual(w, A @ u)))
        True
        >>> reference = energies(A, w, kind, u)
        >>> all(np.isclose(energy[key], reference[key]) for key in reference)
        True
    """
    topo = terms.topology
    n, m = topo.n_vertices, topo.n_faces
    x = u[:n]
    F = u[n:].reshape(m, 3, 3)                     # [t, c, k] = f_t[k, c]
    uniform = bool((terms.edge_weights == 1.0).all())
    worst = edge = frame = 0.0
    for lo in range(0, m, chunk):
        block = slice(lo, min(lo + chunk, m))
        # (b, 3 half-edges, 3 coordinates): x_dest - x_origin - (a1 f[:, 0] + a2 f[:, 1]).
        r = np.take(x, topo.halfedge_dest[3 * lo: 3 * block.stop], axis=0).reshape(-1, 3, 3)
        r -= np.take(x, topo.halfedge_origin[3 * lo: 3 * block.stop], axis=0).reshape(r.shape)
        r -= np.matmul(terms.coefficients[block], F[block, :2])
        if not uniform:
            r *= np.sqrt(terms.edge_weights[block])[:, :, None]
        flat = r.reshape(-1)
        edge += float(np.einsum("i,i->", flat, flat))
        worst = max(worst, float(flat.max(initial=0.0)), -float(flat.min(initial=0.0)))
    inner = terms.interior_edges
    rows = np.arange(len(inner)) if frame_rows is None else np.asarray(frame_rows)
    for lo in range(0, len(rows), chunk):
        q = rows[lo:lo + chunk]
        left, right = np.take(topo.edge_faces, np.take(inner, q), axis=0).T
        R = transition_rotations(np.take(terms.transition, q, axis=0))   # (b, d, c)
        # f_R[k, c] - sum_d f_L[k, d] R[d, c], as [b, c, k].
        r = np.take(F, right, axis=0) - np.matmul(np.swapaxes(R, 1, 2),
                                                  np.take(F, left, axis=0))
        r *= np.sqrt(frame_weight * np.take(terms.frame_weights, q))[:, None, None]
        flat = r.reshape(-1)
        frame += float(np.einsum("i,i->", flat, flat))
        worst = max(worst, float(flat.max(initial=0.0)), -float(flat.min(initial=0.0)))
    return worst, {"edge": edge, "frame": frame}


def max_weighted_residual(weights: np.ndarray, residual: np.ndarray) -> float:
    """``max |sqrt(weights) * residual|`` over rows and columns of a (rows, 3) ``A @ u``
    (column by column, without (rows, 3) temporaries); 0 for no rows."""
    if not len(residual):
        return 0.0
    worst = np.abs(residual[:, 0])
    for c in range(1, residual.shape[1]):
        np.maximum(worst, np.abs(residual[:, c]), out=worst)
    worst *= np.sqrt(weights)
    return float(worst.max())
