"""The nearest surface: a nonlinear fit of vertex positions to target fundamental forms.

The linear solve of Eq. (5) is exact for integrable forms. For forms that no surface has
(noisy, edited, blended or constrained ones) its frames are not rotations, so the answer
shrinks and distorts (Sec. 4 and 6 of the paper). This module returns, from a starting
embedding (the linear answer), the vertex positions whose fundamental forms are nearest to
the requested ones, by Levenberg-Marquardt on the positions directly, minimizing::

    E(x) = 1/2 sum_e ((l_e(x) - L_e) / L_e)^2                  first form (every edge)
         + beta/2 sum_e wrap(theta_e(x) - Theta_e)^2            second form (interior edges)
         + 1/2 sum_v w_v |x_v - p_v|^2 / s^2                    soft position handles
         + 1/2 sum_t w_t sum_c |x_tc - x_t0 - F_t a_tc|^2 / s^2  orientation handles

with ``l_e`` and ``theta_e`` the edge lengths and signed dihedral angles of ``x`` (the
conventions of :mod:`solver.forms`), ``s`` the mean target length and ``F_t a_tc`` the target
edge vectors of a face whose frame is prescribed (Eq. 3 with that frame). Hard position
handles are eliminated. In the plane (``dim=2``, for parameterization) the second form is
identically 0 and is replaced by a one-sided penalty on the signed area of each face
relative to its target area, which pushes flipped and collapsing faces back without pulling
on the others::

    + gamma/2 sum_t (A_t^0 / mean A^0) min(0, A_t(x) / A_t^0 - a_min)^2

Every residual is dimensionless, so the weights mean the same at every scale; ``beta`` is
the weight of a radian of dihedral angle against a relative length change of 1 (a thin
shell's bending against its stretching). Every edge weighs the same by default; the
``"area"`` weighting of :class:`FormTargets` uses a thin shell's density-independent weights
(:func:`form_weights`). Why these energies and weights, with measurements:
``docs/refinement.md``.

Each iteration builds the Gauss-Newton matrix ``J^T J`` directly in its fixed block sparsity
pattern (3x3 blocks between vertices that share a residual: one scatter of per-residual outer
products, no sparse matrix product), damps it (``+ lambda diag``) and factorizes it with
:func:`solver.linalg.factorize`. The pattern never changes between iterations, so backends
that keep their analysis per pattern reuse it; and a factorization serves the next steps too
(one back-substitution each) while its quadratic model still predicts the decrease well.
Steps are shortened by backtracking before the damping grows. A step is kept only when it
lowers ``E``, so the result is never worse than the start.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from .linalg import SingularSystemError, factorize
from .metrics import summary, wrap_angle
from .topology import MeshTopology

ANGLE_WEIGHT = 0.005
"""Default ``beta`` where forms are prescribed (reconstruct, interpolate): the weight of a
radian of dihedral angle against a relative length change of 1. Small: lengths are kept and
the angles give way, which is what noisy, scaled and blended forms need (docs/refinement.md)."""
DEFORM_ANGLE_WEIGHT = 0.3
"""Default ``beta`` for deformations, whose targets are the rest forms: stiffer bending,
smoother shapes under conflicting handles (measured against libigl's ARAP in
docs/refinement.md)."""
AREA_WEIGHT = 100.0
"""Default ``gamma`` (planar fits only): weight of the one-sided signed-area residual."""
AREA_FLOOR = 0.2
"""Planar fits: a face whose signed area falls below this fraction of its target area (or
flips) pays ``gamma/2 (A/A0 - AREA_FLOOR)^2``; larger faces pay nothing."""
HARD_FRAME_WEIGHT = 1e3
"""Weight standing in for a hard orientation handle (not eliminable in positions)."""
MAX_ITERATIONS = 50
TOLERANCE = 1e-4
"""Stop after a full Gauss-Newton step that moved no vertex by more than this fraction of
the mean target edge length (an energy criterion fails here: where the forms conflict, E
stays large at the optimum, so its relative decrease says little about the positions)."""
ENERGY_TOLERANCE = 1e-3
"""... or lowered E by less than this fraction of E (the slow tail of Gauss-Newton where
large residuals remain, e.g. strong deformations: measured to change the result's mean
length and angle errors in the fourth digit)."""
EXACT_ENERGY = 1e-24  # E below this: the forms are met to round-off
FORMS_TOLERANCE = 1e-9
"""Largest relative length error and angle error (rad) of an embedding that "has" the forms:
then there is nothing to refine."""
STEP_FRACTIONS = (1.0, 0.5, 0.25, 0.1)  # of a Gauss-Newton step tried before more damping
ARMIJO = 1e-4  # sufficient decrease: E(x + a d) < E(x) + ARMIJO a g.d
MAX_FROZEN_STEPS = 6  # steps on one factorization before it is rebuilt at the current X
FROZEN_GAIN = 0.5  # rebuild earlier when a step lowers E by less than this x its prediction
FROZEN_REACH = 0.5  # ... or moved a vertex by more than this many mean edge lengths
INITIAL_DAMPING = 1e-9
"""lambda of the first step, relative to diag(J^T J): a plain Gauss-Newton step. A larger
start (1e-4 before) holds back the soft bending modes, whose curvature is far below the
stretching diagonal: each step then closed only a small fraction of their gap, and the
refinement crawled through a long tail of iterations (rocker-arm, noisy angles: 16
iterations and 4 factorizations against 2 and 1 to a lower energy; docs/refinement.md)."""
MIN_DAMPING = 1e-12  # the Nielsen update never lowers lambda below this
REFUSED_DAMPING = 1e-4  # at least this lambda after a fresh step that no backtracking saved
MAX_DAMPING = 1e12  # relative damping at which a step is declared impossible
DEGENERATE = 1e-12  # floor of |N|^2 / s^4 for the dihedral gradient of collapsed faces


@dataclass(frozen=True)
class FormTargets:
    """What the refined surface should have.

    Attributes:
        topology: connectivity (n vertices, m faces, E edges).
        lengths: (E,) float64 > 0 target edge lengths.
        angles: (E,) float64 target dihedral angles (ignored for dim=2 and on the boundary).
        angle_weight: ``beta`` (>= 0).
        area_weight: ``gamma`` (>= 0; dim=2 only). Target areas come from ``lengths``.
        weighting: ``"uniform"`` (every edge alike, the default) or ``"area"``
            (:func:`form_weights`: a thin shell's density-independent weights).
    """

    topology: MeshTopology
    lengths: np.ndarray
    angles: np.ndarray
    angle_weight: float = ANGLE_WEIGHT
    area_weight: float = AREA_WEIGHT
    weighting: str = "uniform"


@dataclass(frozen=True)
class Handles:
    """Position and orientation targets.

    Attributes:
        fixed: (h,) int64 vertices kept exactly where the start embedding has them.
        soft_vertices: (p,) int64; soft_positions (p, dim); soft_weights (p,) > 0.
        frame_faces: (q,) int64 faces with a prescribed orientation; frame_edges (q, 2, dim)
            their target edge vectors ``x_t1 - x_t0`` and ``x_t2 - x_t0``; frame_weights (q,).
    """

    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    soft_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    soft_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    soft_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_faces: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    frame_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class Refinement:
    """Result of :func:`refine`.

    Attributes:
        vertices: (n, dim) float64 refined positions (fixed vertices copied bit for bit).
        report: ``refined`` (bool), ``converged``, ``iterations``, ``rejected_steps``,
            ``factorizations``, ``solves`` (back-substitutions),
            ``seconds``, ``energy_before`` / ``energy_after``, ``before`` / ``after`` residual
            summaries (:func:`form_residuals`), ``stop_reason``.
    """

    vertices: np.ndarray
    report: dict[str, Any]


# ----------------------------------------------------------------------------- geometry


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


def hinge_angles(X: np.ndarray, hinge: np.ndarray, floor: float = 0.0,
                 gradients: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed dihedral angles (k,) of hinges (k, 4) of ``X`` (n, 3), and their gradients.

    The angle is that of :func:`solver.forms.dihedral_angles`. Gradients (k, 4, 3) with
    respect to ``[x_i, x_j, x_a, x_b]`` follow Bridson et al. 2003 (translation invariant:
    they sum to 0); ``floor`` bounds ``|N|^2`` (twice the face area, squared) from below so
    collapsed faces give large but finite gradients.
    """
    xi, xj, xa, xb = (X[hinge[:, c]] for c in range(4))
    e = xj - xi
    elen = np.sqrt(np.einsum("ij,ij->i", e, e))
    n_left = np.cross(e, xa - xi)
    n_right = np.cross(xi - xj, xb - xj)
    q_left = np.maximum(np.einsum("ij,ij->i", n_left, n_left), floor)
    q_right = np.maximum(np.einsum("ij,ij->i", n_right, n_right), floor)
    sin = np.einsum("ij,ij->i", np.cross(n_left, n_right), e) / np.where(elen > 0, elen, 1.0)
    cos = np.einsum("ij,ij->i", n_left, n_right)
    theta = np.arctan2(sin, cos)
    if not gradients:
        return theta, None
    safe = np.where(elen > 0, elen, 1.0)[:, None]
    u_left = n_left / q_left[:, None]
    u_right = n_right / q_right[:, None]
    dot = lambda p, q: np.einsum("ij,ij->i", p, q)[:, None] / safe  # noqa: E731
    g_a = -safe * u_left
    g_b = -safe * u_right
    g_i = -(dot(xa - xj, e) * u_left + dot(xb - xj, e) * u_right)
    g_j = dot(xa - xi, e) * u_left + dot(xb - xi, e) * u_right
    return theta, np.stack([g_i, g_j, g_a, g_b], axis=1)


def signed_areas(X: np.ndarray, faces: np.ndarray, gradients: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed areas (m,) of planar faces of ``X`` (n, 2), and gradients (m, 3, 2)."""
    p0, p1, p2 = (X[faces[:, c]] for c in range(3))
    area = 0.5 * ((p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1])
                  - (p1[:, 1] - p0[:, 1]) * (p2[:, 0] - p0[:, 0]))
    if not gradients:
        return area, None
    perp = lambda v: np.stack([v[:, 1], -v[:, 0]], axis=1)  # noqa: E731 - d(A)/d(corner)
    return area, 0.5 * np.stack([perp(p1 - p2), perp(p2 - p0), perp(p0 - p1)], axis=1)


def form_weights(topology: MeshTopology, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-edge weights (E,) of the length and of the dihedral-angle residuals.

    They make the energy a discretization of a thin shell's (stretching ``int eps^2 dA``,
    bending ``int (kappa - kappa0)^2 dA``; Grinspun et al. 2003, Froehlich and Botsch 2011),
    so that it does not depend on the sampling density (the paper's Fig. 2): the length
    residual of edge e weighs ``A_e`` (a third of its faces' areas) and its angle residual
    ``L_e^2 / A_e``, each divided by its mean so that a uniform mesh has weights 1.
    Areas come from the target lengths (Heron); faces of zero area get the smallest
    positive area of the mesh.
    """
    from .frames import face_edge_lengths, triangle_areas

    areas = triangle_areas(face_edge_lengths(topology, lengths))
    positive = areas[areas > 0]
    areas = np.maximum(areas, positive.min() if len(positive) else 1.0)
    faces = topology.edge_faces
    edge_area = np.where(faces >= 0, areas[np.maximum(faces, 0)], 0.0).sum(axis=1) / 3.0
    length_weights = edge_area / edge_area.mean()
    bending = lengths**2 / edge_area
    return length_weights, bending / bending.mean()


def form_residuals(X: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
                   angles: np.ndarray) -> dict[str, Any]:
    """How far the forms of ``X`` (n, 3) are from target forms.

    Returns summaries (:func:`solver.metrics.summary`: mean, rms, max, p95 of absolute
    values) of the relative length error ``l/L - 1`` over every edge (``length_error``), of
    the dihedral-angle error in radians over interior edges (``angle_error``), and
    ``length_ratio`` = mean of ``l/L``. For a planar ``X`` (n, 2) the angle error is 0.
    """
    edges = topology.edges
    current = np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1)
    out: dict[str, Any] = {"length_error": summary(current / lengths - 1.0),
                           "length_ratio": float(np.mean(current / lengths))
                           if len(lengths) else 1.0}
    if X.shape[1] == 3:
        inner, hinge = hinges(topology)
        theta, _ = hinge_angles(X, hinge, gradients=False)
        out["angle_error"] = summary(wrap_angle(theta - angles[inner]))
    else:
        out["angle_error"] = summary(np.zeros(0))
    return out


def reproduces(X: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
               angles: np.ndarray) -> bool:
    """Whether ``X`` (n, 3) or (n, 2) has the target forms: every relative length error and
    angle error (rad) within :data:`FORMS_TOLERANCE` (then there is nothing to refine)."""
    residual = form_residuals(X, topology, lengths, angles)
    return bool(max(residual["length_error"]["max"], residual["angle_error"]["max"])
                <= FORMS_TOLERANCE)


# ------------------------------------------------------------------------ the residuals


@dataclass
class _Group:
    """One kind of residual: ``rows`` residuals, each touching ``q`` vertices."""

    vertices: np.ndarray          # (rows, q) int64
    evaluate: Any                 # X -> (r (rows,), G (rows, q, dim) or None)
    hinge: bool = False                 # rows are hinges [i, j, a, b]
    gradient_index: np.ndarray | None = None   # positions in J^T r of the kept entries
    gradient_select: np.ndarray | None = None  # kept gradient entries (None: all)
    # J^T J's upper triangle: the products G_k[r] G_l[c] of the slot pairs k <= l (see
    # _Objective._build_pattern), where each lands in the matrix's values, and which are
    # gathered first (None: all, in order).
    diag_r: np.ndarray | None = None     # diagonal blocks: entries (r, c), r <= c
    diag_c: np.ndarray | None = None
    diag_scatter: np.ndarray | None = None
    diag_gather: np.ndarray | None = None
    pair_k: np.ndarray | None = None     # off-diagonal blocks: slot pairs k < l
    pair_l: np.ndarray | None = None
    scatter: np.ndarray | None = None
    gather: np.ndarray | None = None
    twice: tuple[np.ndarray, np.ndarray] | None = None  # degenerate hinges only


class _Objective:
    """The weighted residuals of :func:`refine` and the block pattern of ``J^T J``."""

    def __init__(self, targets: FormTargets, handles: Handles, dim: int) -> None:
        topo = targets.topology
        self.dim = dim
        self.n = topo.n_vertices
        self.scale = float(np.mean(targets.lengths))
        self.groups: list[_Group] = []
        if targets.weighting == "area":
            length_weights, hinge_weights = form_weights(topo, targets.lengths)
        else:
            length_weights = hinge_weights = np.ones(topo.n_edges)
        self._add_lengths(topo.edges, targets.lengths, length_weights)
        if dim == 3 and targets.angle_weight > 0:
            inner, hinge = hinges(topo)
            self._add_hinges(hinge, targets.angles[inner],
                             targets.angle_weight * hinge_weights[inner])
        if dim == 2 and targets.area_weight > 0:
            self._add_areas(topo, targets.lengths, targets.area_weight)
        if len(handles.soft_vertices):
            self._add_soft_positions(handles)
        if len(handles.frame_faces):
            self._add_frames(topo.faces, handles)
        self.free = np.ones(self.n, dtype=bool)
        self.free[handles.fixed] = False
        self.free &= topo.is_referenced
        key = self._pattern_key(topo)
        cached = _PATTERNS.get(key)
        if cached is None:
            self._build_pattern()
            _PATTERNS.put(key, self._pattern_state())
        else:
            self._restore_pattern(cached)

    # -- residual groups (each returns weighted residuals and their gradients)

    def _add_lengths(self, edges: np.ndarray, L: np.ndarray, weights: np.ndarray) -> None:
        w = np.sqrt(weights)

        def evaluate(X: np.ndarray, grad: bool = True):
            d = X[edges[:, 1]] - X[edges[:, 0]]
            length = np.sqrt(np.einsum("ij,ij->i", d, d))
            r = w * (length / L - 1.0)
            if not grad:
                return r, None
            unit = d * (w / (np.where(length > 0, length, 1.0) * L))[:, None]
            return r, np.stack([-unit, unit], axis=1)

        self.groups.append(_Group(edges, evaluate))

    def _add_hinges(self, hinge: np.ndarray, target: np.ndarray, weights: np.ndarray) -> None:
        w = np.sqrt(weights)
        floor = DEGENERATE * self.scale**4

        def evaluate(X: np.ndarray, grad: bool = True):
            theta, G = hinge_angles(X, hinge, floor, grad)
            r = w * wrap_angle(theta - target)
            return r, (None if G is None else w[:, None, None] * G)

        self.groups.append(_Group(hinge, evaluate, hinge=True))

    def _add_areas(self, topo: MeshTopology, L: np.ndarray, weight: float) -> None:
        from .frames import face_edge_lengths, triangle_areas

        area0 = np.maximum(triangle_areas(face_edge_lengths(topo, L)),
                           DEGENERATE * self.scale**2)
        w = np.sqrt(weight * area0 / area0.mean())  # area-weighted like the lengths
        c = w / area0
        faces = topo.faces

        def evaluate(X: np.ndarray, grad: bool = True):
            # One-sided: only faces shrunk below AREA_FLOOR of their area, or flipped, pay;
            # the others are left to the lengths (a two-sided area term costs length accuracy).
            area, G = signed_areas(X, faces, grad)
            r = np.minimum(c * area - AREA_FLOOR * w, 0.0)
            if G is None:
                return r, None
            return r, np.where(r < 0, c, 0.0)[:, None, None] * G

        self.groups.append(_Group(faces, evaluate))

    def _add_soft_positions(self, h: Handles) -> None:
        w = np.sqrt(h.soft_weights) / self.scale
        eye = np.broadcast_to(np.eye(self.dim), (len(w), self.dim, self.dim))
        G = (w[:, None, None] * eye).reshape(-1, 1, self.dim)
        self.soft_positions = np.array(h.soft_positions, dtype=np.float64)

        # One residual per coordinate: rows (p * dim,), each touching one vertex.
        def evaluate(X: np.ndarray, grad: bool = True):
            r = (w[:, None] * (X[h.soft_vertices] - self.soft_positions)).ravel()
            return r, (G if grad else None)

        self.groups.append(_Group(np.repeat(h.soft_vertices[:, None], self.dim, axis=0),
                                  evaluate))

    def _add_frames(self, faces: np.ndarray, h: Handles) -> None:
        F = faces[h.frame_faces]
        pairs = np.concatenate([F[:, [0, 1]], F[:, [0, 2]]])          # (2q, 2)
        w = np.tile(np.sqrt(h.frame_weights), 2) / self.scale
        dim = self.dim
        eye = np.eye(dim)
        block = np.stack([-eye, eye], axis=0)                           # (2, dim, dim)
        G = (w[:, None, None, None] * block[None]).transpose(0, 2, 1, 3)  # (2q, dim, 2, dim)
        G = G.reshape(-1, 2, dim)
        self.frame_edges = np.array(h.frame_edges, dtype=np.float64)

        def evaluate(X: np.ndarray, grad: bool = True):
            targets = np.concatenate([self.frame_edges[:, 0], self.frame_edges[:, 1]])
            d = X[pairs[:, 1]] - X[pairs[:, 0]] - targets
            return (w[:, None] * d).ravel(), (G if grad else None)

        self.groups.append(_Group(np.repeat(pairs, dim, axis=0), evaluate))

    # -- the pattern of J^T J's upper triangle over the free coordinates

    _OBJECTIVE_FIELDS = ("index", "n_free", "ordering_groups", "indptr", "indices", "nnz",
                         "diagonal_positions")
    _GROUP_FIELDS = ("gradient_index", "gradient_select", "diag_r", "diag_c", "diag_scatter",
                     "diag_gather", "pair_k", "pair_l", "scatter", "gather", "twice")

    def _pattern_key(self, topology: MeshTopology) -> bytes:
        """Digest of everything :meth:`_build_pattern` depends on: the faces, the free
        vertices and each group's vertex rows."""
        digest = hashlib.blake2b(digest_size=16)
        digest.update(repr((self.n, self.dim, len(self.groups))).encode())
        for array in (topology.faces, self.free, *(g.vertices for g in self.groups)):
            digest.update(repr(array.shape).encode())
            digest.update(np.ascontiguousarray(array).tobytes())
        return digest.digest()

    def _pattern_state(self) -> dict[str, Any]:
        """The arrays :meth:`_build_pattern` made (shared, never written to afterwards)."""
        return {"objective": {f: getattr(self, f) for f in self._OBJECTIVE_FIELDS},
                "groups": [{f: getattr(g, f) for f in self._GROUP_FIELDS}
                           for g in self.groups]}

    def _restore_pattern(self, state: dict[str, Any]) -> None:
        for name, value in state["objective"].items():
            setattr(self, name, value)
        for g, fields in zip(self.groups, state["groups"], strict=True):
            for name, value in fields.items():
                setattr(g, name, value)

    def _build_pattern(self) -> None:
        """The scalar CSR pattern of the upper triangle of ``J^T J`` over the free
        coordinates (every diagonal entry stored, for the damping) and, per group, where
        each product of its residuals' gradients lands.

        ``J^T J = sum_rows sum_(k, l) G_k G_l^T`` over a row's vertex slots; only slot pairs
        k <= l are multiplied (their product, or its transpose when vertex l comes first,
        is an upper block; the lower triangle of a diagonal block is dropped), then
        scattered with one ``bincount`` per group straight into the values of the matrix
        that the factorization reads (:func:`solver.linalg.factorize` with
        ``triangle="upper"``): no sparse product, no format conversion.
        """
        dim = self.dim
        index = np.full(self.n, -1, dtype=np.int64)
        index[self.free] = np.arange(int(self.free.sum()))
        self.index = index
        n_free = self.n_free = int(self.free.sum())
        # Ordering hint of the factorization: a vertex's dim coordinates couple alike.
        self.ordering_groups = np.repeat(np.arange(n_free), dim)
        # Block pattern: upper vertex pairs (a <= b) that share a residual, every diagonal.
        parts = [np.arange(n_free, dtype=np.int64) * (n_free + 1)]
        for g in self.groups:
            local = index[g.vertices]
            q = local.shape[1]
            if g.hinge:  # its other pairs are edges, present in the length group
                g_k, g_l = np.array([2]), np.array([3])
            else:
                g_k, g_l = np.triu_indices(q, 1)
            a, b = local[:, g_k], local[:, g_l]
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            parts.append(np.where(lo >= 0, lo * n_free + hi, -1).ravel())
        pattern = np.unique(np.concatenate(parts))
        pattern = pattern[pattern >= 0]
        block_rows, block_cols = np.divmod(pattern, max(n_free, 1))
        block_indptr = np.searchsorted(block_rows, np.arange(n_free + 1))
        # Scalar CSR of the upper triangle: row dim*a + r holds the diagonal block's entries
        # c >= r, then dim entries for each upper block (a, b > a), in column order.
        blocks_in_row = np.diff(block_indptr)                       # diagonal included
        r = np.arange(dim)
        row_length = (dim - r)[None, :] + dim * (blocks_in_row[:, None] - 1)  # (n_free, dim)
        indptr = np.zeros(n_free * dim + 1, dtype=np.int64)
        np.cumsum(row_length.ravel(), out=indptr[1:])
        self.indptr = indptr.astype(np.int32)
        # Column of every stored entry, block by block.
        diag_cols = np.concatenate([np.arange(c, dim) for c in range(dim)])  # per row r
        rank = np.arange(len(pattern)) - block_indptr[block_rows]     # 0 = diagonal block
        indices = np.empty(indptr[-1], dtype=np.int64)
        diag_rows = np.repeat(np.arange(dim), dim - np.arange(dim))
        start = indptr[:-1].reshape(n_free, dim)
        # Diagonal blocks.
        pos = start[:, diag_rows] + (diag_cols - diag_rows)[None, :]
        indices[pos.ravel()] = (np.arange(n_free)[:, None] * dim + diag_cols[None, :]).ravel()
        self.diagonal_positions = start.ravel()  # row dim*a + r starts at its entry (r, r)
        # Off-diagonal blocks.
        off = rank > 0
        a, b, k = block_rows[off], block_cols[off], rank[off]
        rr, cc = np.meshgrid(r, r, indexing="ij")
        pos = (start[a][:, rr] + (dim - rr) + dim * (k[:, None, None] - 1) + cc)
        indices[pos.ravel()] = (b[:, None, None] * dim + cc).ravel()
        self.indices = indices.astype(np.int32)
        self.nnz = int(indptr[-1])

        upper_r, upper_c = np.triu_indices(dim)                       # diagonal blocks
        if not n_free:  # every vertex fixed: nothing is gathered (keep the indexing valid)
            start = np.zeros((1, dim), dtype=np.int64)
        for g in self.groups:
            local = index[g.vertices]
            q = local.shape[1]
            slots = (local[:, :, None] * dim + np.arange(dim)).ravel()
            # Where each (row, vertex, coordinate) gradient entry lands in J^T r.
            g.gradient_select = None if (local >= 0).all() else np.flatnonzero(slots >= 0)
            g.gradient_index = slots if g.gradient_select is None else slots[g.gradient_select]
            # Diagonal blocks: G_k[r] G_k[c] for r <= c, at (dim a + r, dim a + c).
            g.diag_r, g.diag_c = upper_r, upper_c
            diag = start[np.maximum(local, 0)][:, :, upper_r] + (upper_c - upper_r)
            diag_keep = np.repeat(local >= 0, len(upper_r))
            # Off-diagonal pairs k < l: P[r, c] = G_k[r] G_l[c] lands at block (a, b) entry
            # (r, c) when a < b, at block (b, a) entry (c, r) when a > b.
            g.pair_k, g.pair_l = np.triu_indices(q, 1)
            a, b = local[:, g.pair_k], local[:, g.pair_l]
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            valid = lo >= 0
            block = np.searchsorted(pattern, np.where(valid, lo * n_free + hi, 0))
            shift = dim * (block - block_indptr[np.maximum(lo, 0)] - 1)  # (rows, pairs)
            first = start[np.maximum(lo, 0)]                               # (rows, pairs, dim)
            forward = first[:, :, :, None] + (dim - rr) + cc               # [.., r, c]
            backward = np.swapaxes(forward, 2, 3)                          # rows of b first
            off = np.where((a > b)[:, :, None, None], backward, forward) + shift[:, :, None,
                                                                                 None]
            off_keep = np.repeat(valid.ravel(), dim * dim)
            # Two slots of one vertex (only in degenerate hinges): fold the pair's product
            # and its transpose onto the diagonal block's upper triangle.
            same = (a == b) & valid
            if same.any():
                base = first[same]                                          # (s, dim)
                lo_rc, hi_rc = np.minimum(rr, cc), np.maximum(rr, cc)
                off[same] = base[:, lo_rc] + (hi_rc - lo_rc)
            g.diag_scatter, g.diag_gather = self._scatter(diag.ravel(), diag_keep)
            g.scatter, g.gather = self._scatter(off.ravel(), off_keep)
            g.twice = None
            if same.any():  # the diagonal entries of P + P^T count twice
                twice = (same[:, :, None, None] & (rr == cc)).ravel()
                g.twice = (np.flatnonzero(twice), off.ravel()[twice])

    def _scatter(self, dest: np.ndarray, keep: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """(positions of the kept products in the matrix values, int32 where they fit;
        indices of the kept products, None when all are kept)."""
        gather = None if keep.all() else np.flatnonzero(keep)
        dest = dest if gather is None else dest[gather]
        return (dest.astype(np.int32) if self.nnz < 2**31 else dest), gather

    # -- evaluation

    def energy(self, X: np.ndarray) -> float:
        """E(X) (see the module docstring)."""
        return 0.5 * sum(float(np.dot(r, r)) for r in
                         (g.evaluate(X, False)[0] for g in self.groups))

    def normal_equations(self, X: np.ndarray, matrix: bool = True,
                         ) -> tuple[float, sp.csr_array | None, np.ndarray]:
        """(E, the upper triangle of J^T J over the free coordinates (canonical CSR, every
        diagonal entry stored; None unless ``matrix``), J^T r (n_free * dim,))."""
        dim = self.dim
        values = np.zeros(self.nnz) if matrix else None
        gradient = np.zeros(self.n_free * dim)
        energy = 0.0
        for g in self.groups:
            r, G = g.evaluate(X)
            energy += 0.5 * float(np.dot(r, r))
            contrib = (r[:, None, None] * G).ravel()            # (rows * q * dim,)
            if g.gradient_select is not None:
                contrib = contrib[g.gradient_select]
            gradient += np.bincount(g.gradient_index, contrib, minlength=len(gradient))
            if values is not None:
                diag = (G[:, :, g.diag_r] * G[:, :, g.diag_c]).ravel()
                values += np.bincount(g.diag_scatter, diag if g.diag_gather is None
                                      else diag[g.diag_gather], minlength=len(values))
                off = (G[:, g.pair_k, :, None] * G[:, g.pair_l, None, :]).ravel()
                values += np.bincount(g.scatter, off if g.gather is None else off[g.gather],
                                      minlength=len(values))
                if g.twice is not None:
                    values += np.bincount(g.twice[1], off[g.twice[0]], minlength=len(values))
        if values is None:
            return energy, None, gradient
        n = self.n_free * dim
        H = sp.csr_array((values, self.indices, self.indptr), shape=(n, n))
        H.has_canonical_format = True
        return energy, H, gradient


def _quadratic_form(upper: sp.csr_array, diagonal: np.ndarray, x: np.ndarray) -> float:
    """x^T H x for the symmetric H whose upper triangle is ``upper`` (its diagonal
    ``diagonal``)."""
    return float(2.0 * (x @ (upper @ x)) - x @ (diagonal * x))


PATTERN_CACHE_BYTES = 256 * 2**20
"""Bytes of Gauss-Newton patterns (the index arrays of :meth:`_Objective._build_pattern`,
about 1.5 KB per face) a process keeps, most recent first: a new refinement of a mesh it
has seen (another request, another blend value of :func:`solver.interpolate`, a new
handle set of the same sizes) skips the set-up (~0.1 s at 20K faces). 0 disables it."""


class _PatternCache:
    """LRU of Gauss-Newton patterns within :data:`PATTERN_CACHE_BYTES`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._entries: OrderedDict[bytes, tuple[dict[str, Any], int]] = OrderedDict()
        self.counts = {"computed": 0, "cached": 0}

    def get(self, key: bytes) -> dict[str, Any] | None:
        with self._lock:
            entry = self._entries.get(key)
            self.counts["computed" if entry is None else "cached"] += 1
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return entry[0]

    def put(self, key: bytes, state: dict[str, Any]) -> None:
        size = _state_bytes(state)
        with self._lock:
            if size > PATTERN_CACHE_BYTES:
                return
            self._entries[key] = (state, size)
            while sum(n for _, n in self._entries.values()) > PATTERN_CACHE_BYTES:
                self._entries.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.counts = dict.fromkeys(self.counts, 0)

    def info(self) -> dict[str, int]:
        with self._lock:
            return {"entries": len(self._entries),
                    "bytes": sum(n for _, n in self._entries.values()), **self.counts}


def _state_bytes(state: Any) -> int:
    """Bytes of the numpy arrays in a nested pattern state."""
    if isinstance(state, np.ndarray):
        return state.nbytes
    if isinstance(state, dict):
        return sum(_state_bytes(v) for v in state.values())
    if isinstance(state, list | tuple):
        return sum(_state_bytes(v) for v in state)
    return 0


_PATTERNS = _PatternCache()


def pattern_cache_info() -> dict[str, int]:
    """``entries`` and ``bytes`` kept, and how many refinements ``computed`` or reused
    (``cached``) their Gauss-Newton pattern."""
    return _PATTERNS.info()


def clear_pattern_cache() -> None:
    """Forget every kept pattern and reset :func:`pattern_cache_info`'s counters."""
    _PATTERNS.clear()


# --------------------------------------------------------------------------- the solver


class Refiner:
    """Levenberg-Marquardt fit of positions to target forms, built once per problem.

    Building it computes the block pattern of ``J^T J`` (the costly set-up); :meth:`run`
    can then be called for many starts and handle targets (e.g. each drag of a deformation
    session) with the same fixed vertices.

    Args:
        targets: :class:`FormTargets`.
        handles: optional :class:`Handles`; their target values may change per :meth:`run`.
        dim: 3, or 2 for a planar fit (parameterization).
        backend: sparse factorization backend (:func:`solver.linalg.factorize`).
    """

    def __init__(self, targets: FormTargets, handles: Handles | None = None, dim: int = 3,
                 backend: str = "auto") -> None:
        handles = handles or Handles(soft_positions=np.zeros((0, dim)),
                                     frame_edges=np.zeros((0, 2, dim)))
        self.targets = targets
        self.backend = backend
        self.objective = _Objective(targets, handles, dim)
        self._kept: tuple[Any, sp.csr_array] | None = None  # see run(keep_factor=True)
        self._kept_damping = INITIAL_DAMPING

    def set_handle_targets(self, soft_positions: np.ndarray | None = None,
                           frame_edges: np.ndarray | None = None) -> None:
        """Replace the soft handle positions (p, dim) and the orientation handles' target
        edge vectors (q, 2, dim) (``None`` keeps the current ones)."""
        if soft_positions is not None:
            self.objective.soft_positions = np.asarray(soft_positions, dtype=np.float64)
        if frame_edges is not None:
            self.objective.frame_edges = np.asarray(frame_edges, dtype=np.float64)

    def energy(self, vertices: np.ndarray) -> float:
        """E of (n, dim) positions (fixed vertices as given)."""
        return self.objective.energy(np.asarray(vertices, dtype=np.float64))

    def reproduces(self, vertices: np.ndarray) -> bool:
        """Whether ``vertices`` already have the target forms (:func:`reproduces`)."""
        t = self.targets
        return reproduces(vertices, t.topology, t.lengths, t.angles)

    def residuals(self, vertices: np.ndarray) -> dict[str, Any]:
        """:func:`form_residuals` of ``vertices`` against the targets."""
        t = self.targets
        return form_residuals(vertices, t.topology, t.lengths, t.angles)

    def run(self, start: np.ndarray, *, soft_positions: np.ndarray | None = None,
            frame_edges: np.ndarray | None = None, max_iterations: int = MAX_ITERATIONS,
            tolerance: float = TOLERANCE, time_limit: float | None = None,
            keep_factor: bool = False, progress: Any = None) -> Refinement:
        """Refine from ``start`` (n, dim); fixed vertices keep their ``start`` positions.

        ``soft_positions`` (p, dim) and ``frame_edges`` (q, 2, dim) replace the handle
        targets given at construction. ``keep_factor``: start from the factorization the
        previous ``keep_factor`` run ended with and keep this run's for the next (for a
        session's drags, which are alike); convergence may then be declared on a step of
        that kept factor, without a fresh factorization to confirm it. See :func:`refine`
        for the rest.
        """
        notify = _iteration_notifier(progress, time_limit)
        clock = time.perf_counter()
        objective = self.objective
        self.set_handle_targets(soft_positions, frame_edges)
        X = np.array(start, dtype=np.float64)
        before = self.residuals(X)
        energy0 = energy = objective.energy(X)
        damping, growth = INITIAL_DAMPING, 2.0
        iterations = rejected = factorizations = solves = 0
        stop, converged = "max_iterations", False
        trace, steps = [energy0], []
        # The last factorized damped matrix and its J^T J; with ``keep_factor`` the previous
        # run's, as a start (consecutive drags of a session are alike).
        factor, model = self._kept if keep_factor and self._kept else (None, None)
        if factor is not None:
            damping = self._kept_damping
        fresh = False  # whether ``factor`` was computed at the current X
        # Gain ratio of the last step taken with ``factor`` (how well its model predicted).
        factor_gain = 1.0 if factor is not None else 0.0
        frozen_steps = 0
        while iterations < max_iterations and objective.n_free and not converged:
            if time_limit is not None and time.perf_counter() - clock > time_limit:
                stop = "time_limit"
                break
            iterations += 1
            refresh = factor is None or frozen_steps >= MAX_FROZEN_STEPS
            energy, H, g = objective.normal_equations(X, matrix=refresh)
            if energy <= EXACT_ENERGY:
                stop, converged = "exact", True
                break
            accepted = False
            while not accepted and damping <= MAX_DAMPING:
                if refresh:
                    factor = None  # frees its analysis for the cache: the next one reuses it
                    try:
                        factor = self._damped_factor(H, damping)
                    except SingularSystemError:
                        damping, rejected = damping * 10.0, rejected + 1
                        continue
                    factorizations += 1
                    model, fresh, frozen_steps, factor_gain = H, True, 0, 0.0
                step = -factor.solve(g)
                solves += 1
                slope = float(g @ step)  # < 0: a descent direction (H + D is SPD)
                # Gain ratio of the full step: actual decrease over the Gauss-Newton model's.
                predicted = -slope - 0.5 * _quadratic_form(
                    model, model.data[objective.diagonal_positions], step)
                found = self._line_search(X, step, energy, slope)
                accepted = found is not None
                if found is None:
                    rejected += 1
                    if fresh:
                        damping = max(damping * growth, REFUSED_DAMPING)
                        growth *= 2.0
                    elif H is None:  # a frozen factor failed: rebuild it here
                        energy, H, g = objective.normal_equations(X)
                    refresh = True
                    continue
                alpha, trial, new_energy = found
                gain = (energy - new_energy) / predicted if predicted > 0 else 0.0
                # A full Gauss-Newton step (fresh matrix, little damping) that barely lowers
                # E: converged. A frozen, shortened or heavily damped step says nothing.
                full = fresh and alpha == 1.0 and damping <= 1.0
                moved = float(np.abs(step).max(initial=0.0)) / objective.scale
                decrease, X, energy = energy - new_energy, trial, new_energy
                trace.append(energy)
                steps.append(moved)
                notify(iterations, factorizations, energy, time.perf_counter() - clock)
                # ... unless E still falls fast (Gauss-Newton's quadratic convergence where the
                # forms are met): then a few more steps are cheap and reach round-off.
                slowing = decrease <= 0.5 * (energy + decrease)
                small = moved <= tolerance or decrease <= ENERGY_TOLERANCE * energy
                if (full and small and slowing) or energy <= EXACT_ENERGY:
                    stop, converged = "converged", True
                elif small and slowing and not fresh:
                    # A small full step on a kept factor whose model just predicted the
                    # decrease well (gain near 1) is as good as a fresh one: that factor is
                    # the Gauss-Newton matrix of a nearby point. Interactive runs
                    # (keep_factor) accept it outright; otherwise confirm with a fresh step.
                    trusted = alpha == 1.0 and damping <= 1.0 and abs(factor_gain - 1.0) <= 0.25
                    if keep_factor or trusted:
                        stop, converged = "converged", True
                    frozen_steps = MAX_FROZEN_STEPS
                if fresh:  # Levenberg-Marquardt's damping update (Nielsen)
                    damping = max(MIN_DAMPING, damping * (
                        max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3) if alpha == 1.0 else 10.0))
                    growth = 2.0
                # The next step reuses this factor (one back-substitution) while its model
                # still predicts well; otherwise it is rebuilt at the new X.
                fresh, factor_gain = False, gain
                frozen_steps += 1
                # ... nor after a long step: a model built before a move of more than
                # FROZEN_REACH edge lengths was refused in every measured case (x0.8 forms,
                # strong deformations), at the price of a back-substitution and a line search.
                if gain < FROZEN_GAIN or moved > FROZEN_REACH:
                    frozen_steps = MAX_FROZEN_STEPS
            if not accepted:  # no step lowers E: a stationary point to working precision
                stop, converged = "stationary", True
        if not objective.n_free:
            stop, converged = "no_free_vertices", True
        if keep_factor and factor is not None:
            self._kept, self._kept_damping = (factor, model), damping
        return Refinement(vertices=X, report={
            "refined": True,
            "converged": converged,
            "stop_reason": stop,
            "iterations": iterations,
            "rejected_steps": rejected,
            "factorizations": factorizations,
            "solves": solves,
            "energy_before": energy0,
            "energy_after": energy,
            "energy_trace": trace,
            "step_trace": steps,
            "before": before,
            "after": self.residuals(X),
            "angle_weight": self.targets.angle_weight,
            "seconds": time.perf_counter() - clock,
        })

    def _damped_factor(self, H: sp.csr_array, damping: float) -> Any:
        """Factorization of ``H + damping diag(H)`` (Levenberg-Marquardt; the diagonal is
        floored at 1e-9 of its mean, which is also added, so that H + D is definite).
        Raises :class:`SingularSystemError` where the backend finds it singular."""
        positions = self.objective.diagonal_positions
        diag = H.data[positions]
        floor = 1e-9 * float(diag.mean())
        values = H.data.copy()
        values[positions] += damping * np.maximum(diag, floor) + floor
        damped = sp.csr_array((values, H.indices, H.indptr), shape=H.shape)
        damped.has_canonical_format = True
        return factorize(damped, self.backend, triangle="upper",
                         groups=self.objective.ordering_groups)

    def _line_search(self, X: np.ndarray, step: np.ndarray, energy: float, slope: float,
                     ) -> tuple[float, np.ndarray, float] | None:
        """Backtracking along ``step`` (n_free * dim,) from ``X`` (n, dim) at energy
        ``energy`` with directional derivative ``slope`` < 0: the first of
        :data:`STEP_FRACTIONS` that decreases E sufficiently (Armijo), as ``(fraction, new
        positions, new E)``, or None. It costs energies, never factorizations."""
        objective = self.objective
        for alpha in STEP_FRACTIONS:
            trial = X.copy()
            trial[objective.free] += alpha * step.reshape(-1, objective.dim)
            new_energy = objective.energy(trial)
            if np.isfinite(new_energy) and new_energy < energy + ARMIJO * alpha * slope:
                return alpha, trial, new_energy
        return None


def _iteration_notifier(progress: Any, time_limit: float | None) -> Any:
    """``notify(iteration, factorizations, energy, seconds)`` for :meth:`Refiner.run`:
    calls ``progress("refine", fraction)`` and, when ``progress`` has one,
    ``progress.iteration(detail)``; does nothing without ``progress``."""
    if progress is None:
        return lambda *args: None
    detail_hook = getattr(progress, "iteration", None)

    def notify(iteration: int, factorizations: int, energy: float, seconds: float) -> None:
        # A refinement's length is unknown: most end after 2-5 iterations, so the fraction
        # climbs towards 1 as iterations pass (or as the time budget is spent).
        fraction = iteration / (iteration + 3.0)
        if time_limit:
            fraction = max(fraction, seconds / time_limit)
        progress("refine", min(fraction, 0.99))
        if detail_hook is not None:
            detail_hook({"iteration": iteration, "factorizations": factorizations,
                         "energy": energy, "seconds": seconds})

    return notify


def refine(vertices: np.ndarray, targets: FormTargets, handles: Handles | None = None, *,
           max_iterations: int = MAX_ITERATIONS, tolerance: float = TOLERANCE,
           time_limit: float | None = None, backend: str = "auto",
           progress: Any = None) -> Refinement:
    """Vertex positions whose fundamental forms are nearest to ``targets`` (Levenberg-Marquardt).

    Args:
        vertices: (n, dim) float64 start (dim 3, or 2 for a planar fit), e.g. the linear
            answer of Eq. (5). Fixed handle vertices keep these positions.
        targets: :class:`FormTargets` (lengths, angles, weights).
        handles: optional :class:`Handles`.
        max_iterations: Gauss-Newton matrices built (each one factorization, plus one per
            rejected step).
        tolerance: stop after a full Gauss-Newton step that moved no vertex by more than
            ``tolerance`` times the mean target edge length.
        time_limit: optional wall-clock budget in seconds (checked between iterations):
            when it runs out the best iterate is returned, ``converged`` False and
            ``stop_reason`` ``"time_limit"``.
        backend: sparse factorization backend (:func:`solver.linalg.factorize`).
        progress: optional ``progress(stage, fraction)`` callback, called as
            ``progress("refine", fraction)`` after every accepted step; if it also has a
            method ``iteration(detail)``, that gets ``{"iteration", "factorizations",
            "energy", "seconds"}`` of each step (the service's job progress shows them).
    Returns:
        :class:`Refinement`. Its energy is never above the start's: a step is accepted
        only when it lowers E. ``report["converged"]`` is False when the iteration or time
        budget ran out first.

    Example::

        >>> import numpy as np, solver
        >>> from solver.refine import FormTargets, refine
        >>> from solver.topology import build_topology
        >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.2]])
        >>> F = np.array([[0, 1, 2], [2, 1, 3]])
        >>> forms = solver.fundamental_forms(V, F)
        >>> fit = refine(V * 0.9, FormTargets(build_topology(F), forms.lengths, forms.angles))
        >>> bool(fit.report["after"]["length_error"]["max"] < 1e-6)
        True
    """
    dim = np.shape(vertices)[1]
    return Refiner(targets, handles, dim, backend).run(
        vertices, max_iterations=max_iterations, tolerance=tolerance, time_limit=time_limit,
        progress=progress)
