"""The refinement's energy: how far an embedding's fundamental forms are from target ones.

:mod:`solver.refine` minimizes, over vertex positions ``x``::

    E(x) = 1/2 sum_e ((l_e(x) - L_e) / L_e)^2                  first form (every edge)
         + beta/2 sum_e wrap(theta_e(x) - Theta_e)^2            second form (interior edges)
         + 1/2 sum_t |x_c - (1 - t_t) x_a - t_t x_b|^2 / L_ab^2  cap faces (dim 3)
         + 1/2 sum_v w_v |x_v - p_v|^2 / s^2                    soft position handles
         + 1/2 sum_t w_t sum_c |x_tc - x_t0 - F_t a_tc|^2 / s^2  orientation handles

with ``l_e`` and ``theta_e`` the edge lengths and signed dihedral angles of ``x`` (the
conventions of :mod:`solver.mesh.forms`), ``s`` the mean target length and ``F_t a_tc`` the target
edge vectors of a face whose frame is prescribed (Eq. 3 with that frame). Hard position
handles are eliminated. In the plane (``dim=2``, for parameterization) the second form is
identically 0 and is replaced by a one-sided penalty on the signed area of each face
relative to its target area, which pushes flipped and collapsing faces back without pulling
on the others::

    + gamma/2 sum_t (A_t^0 / mean A^0) min(0, A_t(x) / A_t^0 - a_min)^2

A *cap* face (:func:`cap_faces`: its target height under :data:`CAP_HEIGHT` of its longest
edge ``a b``) has no usable dihedral angles: its normal turns over when its apex ``c`` moves
by its height. Its edges' angle residuals are left out, and its apex is held on the base at
the foot ``t_t`` its target lengths give (a linear residual, as stiff as the base's length).

Every residual is dimensionless, so the weights mean the same at every scale; ``beta`` is
the weight of a radian of dihedral angle against a relative length change of 1 (a thin
shell's bending against its stretching). Every edge weighs the same by default; the
``"area"`` weighting of :class:`FormTargets` uses a thin shell's density-independent weights
(:func:`form_weights`). Why these energies and weights, with measurements:
``docs/refinement.md``.

:class:`FormEnergy` holds the residuals as groups (one kind each, a fixed number of vertices
per residual) with their gradients; :mod:`solver.refine.normal_equations` assembles ``J^T J`` from
them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..mesh.embedding_geometry import (
    edge_vectors,
    hinge_angles,
    hinges,
    signed_areas,
)
from ..mesh.metrics import summary, wrap_angle
from ..mesh.topology import MeshTopology
from .energy_weights import (
    ANGLE_WEIGHT,
    AREA_FLOOR,
    AREA_WEIGHT,
)
from .ties import needle_ties, no_ties

FORMS_TOLERANCE = 1e-9
"""Largest relative length error and angle error (rad) of an embedding that "has" the forms:
then there is nothing to refine."""
DEGENERATE = 1e-12  # floor of |N|^2 / s^4 for the dihedral gradient of collapsed faces
NEEDLE_STIFFNESS = 1e4
"""Stiffness of a needle edge's relative length over a mean edge's (``(s / L)^2``): the
refinement's damping does not scale with the diagonal of its vertices
(:meth:`solver.refine.Refiner._damped_factor`). Edges 1e-4 of the mean long (the held-out
irregular mesh of issue 19 and bench.refinement's irregular cases) are 1e8 times as stiff;
the face of the tests has edges 0.04 of the mean long (600 times), where capping the
damping cost a session's kept-factor drags 30% in energy."""
STRETCH_CURVATURE = 100.0
"""Gauss-Newton drops ``r ∇²r`` from the Hessian of a residual's ``r^2 / 2`` as small beside
``∇r ∇r^T``. Across a stretched edge (``r > 0``) that term, ``r / (L l) (I - u u^T)``, is
the edge's only stiffness, and on an edge far shorter than the mesh's mean it is not small:
without it the vertex of a needle edge swings across the edge between iterations, and
the models of the iterations after are refused or crawl (rocker-arm with 30 edges split to
1e-4 of their length, noisy angles: 7 factorizations, 4 with it, ``python -m
bench.refinement --sections time``; the torus with 20 of tests/solver/test_refine.py: 8
and 4). The refinement keeps it where it is at least this many times a mean edge's
stiffness ``1 / s^2``: in practice needle edges only, as a 100-fold smaller ratio also
changed the planar refinement of the beetle, whose stretched edges are long (16 -> 29
iterations with this constant at 1; ``python -m bench.refinement --sections
parameterize``). Never where ``r < 0``: that part is negative and would make the matrix
indefinite."""
CAP_HEIGHT = 1e-3
"""A face whose target height is under this fraction of its longest edge is a cap
(:func:`cap_faces`): its apex is held on its base by a linear residual, and the dihedral
angles of its edges are left out. Those angles move by ~π when the apex moves by the face's
height across the base, so Gauss-Newton's linear model of them holds only for steps
shorter than that: with 9 faces flattened to 1e-6 of their width (``bench.refinement``'s
``irregular + caps``) every iteration took a factorization (rocker-arm 10, stanford-bunny
8); with the apex residual 2. A knight with 5 faces flattened to 2e-5-3e-3 of their width
and 10 needle edges (1e-4 of their length) stalled after 12-21 iterations and 15-22
factorizations under a threshold of 1e-5, and converges in 3 iterations and 2
factorizations under this one for heights up to 1e-4 (4 and 8 at 1e-3, on the threshold;
stalled at 2e-3, above it). That sweep of heights and thresholds was a development
measurement; ``tests/solver/test_refine.py`` checks 1e-6 and 1e-4 (converged in at most 3
factorizations) and 2e-3 (stalled). Needle faces (next to an edge 1e-4 of
the mean long) are caps too: held by their apex residual and their stiff short edge, with
their angles kept the faces flattened 6e-4-1.5e-3 of their width stopped "stationary" at
16 factorizations and 10-50 times the optimum's energy. The residual aims at height 0, so
at the original shape it is the face's height over its base, at most this fraction: among
the shared meshes only nefertiti has such a face (one sliver)."""


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



@dataclass(frozen=True)
class CapFaces:
    """Faces too flat for their dihedral angles (:func:`cap_faces`).

    Attributes:
        faces: (k,) int64 the cap faces.
        corners: (k, 3) int64 their vertices ``[a, b, c]``: the longest edge ``a -> b`` (the
            base, in the face's orientation) and the apex ``c``.
        foot: (k,) float64 ``t``: where the apex sits over the base by the target lengths,
            ``x_c = (1 - t) x_a + t x_b`` up to the face's height (0 <= t <= 1).
        coefficients: (k, 3) float64 ``(t - 1, -t, 1) / L_ab``: the apex residual
            ``(x_c - (1 - t) x_a - t x_b) / L_ab`` is ``sum_p coefficients[p] x_corners[p]``.
        edges: (k, 3) int64 the edges ``a b``, ``b c``, ``c a`` (indices into
            ``topology.edges``).
        lengths: (k, 3) float64 their target lengths.
        is_cap_edge: (E,) bool, the edges of cap faces (their angles are left out).
    """

    faces: np.ndarray
    corners: np.ndarray
    foot: np.ndarray
    coefficients: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray
    is_cap_edge: np.ndarray


def cap_faces(topology: MeshTopology, lengths: np.ndarray) -> CapFaces:
    """The faces whose target height is under :data:`CAP_HEIGHT` of their longest edge: a
    corner of nearly 180°, or a needle (an edge far shorter than the other two). Heights
    come from the target ``lengths`` (E,) float64 (:func:`solver.mesh.frames.triangle_areas`).

    Example:
        >>> import numpy as np
        >>> from solver.mesh.topology import build_topology
        >>> topo = build_topology(np.array([[0, 1, 2], [0, 2, 3]]))
        >>> V = np.array([[0., 0, 0], [2, 0, 0], [1, 1e-7, 0], [0, 1, 0]])
        >>> L = np.linalg.norm(V[topo.edges[:, 1]] - V[topo.edges[:, 0]], axis=1)
        >>> caps = cap_faces(topo, L)
        >>> caps.faces.tolist(), caps.corners.tolist(), caps.foot.round(6).tolist()
        ([0], [[0, 1, 2]], [0.5])
    """
    from ..mesh.frames import face_edge_lengths, triangle_areas

    face_lengths = face_edge_lengths(topology, lengths)          # half-edge k: corner k -> k+1
    longest = face_lengths.max(axis=1)
    height = 2.0 * triangle_areas(face_lengths) / np.where(longest > 0, longest, 1.0)
    faces = np.flatnonzero(height < CAP_HEIGHT * longest)
    base = face_lengths[faces].argmax(axis=1)
    turn = (base[:, None] + np.arange(3)) % 3                     # base, then b -> c, c -> a
    rows = faces[:, None]
    corners = topology.faces[rows, turn]
    edges = topology.halfedge_edge.reshape(-1, 3)[rows, turn]
    L = lengths[edges]
    foot = np.clip(0.5 + (L[:, 2] ** 2 - L[:, 1] ** 2) / (2.0 * L[:, 0] ** 2), 0.0, 1.0)
    coefficients = np.stack([foot - 1.0, -foot, np.ones_like(foot)], axis=1) / L[:, :1]
    is_cap_edge = np.zeros(len(lengths), dtype=bool)
    is_cap_edge[edges.ravel()] = True
    return CapFaces(faces, corners.astype(np.int64), foot, coefficients,
                    edges.astype(np.int64), L, is_cap_edge)


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
    from ..mesh.frames import face_edge_lengths, triangle_areas

    areas = triangle_areas(face_edge_lengths(topology, lengths))
    positive = areas[areas > 0]
    areas = np.maximum(areas, positive.min() if len(positive) else 1.0)
    faces = topology.edge_faces
    edge_area = np.where(faces >= 0, areas[np.maximum(faces, 0)], 0.0).sum(axis=1) / 3.0
    length_weights = edge_area / edge_area.mean()
    bending = lengths**2 / edge_area
    return length_weights, bending / bending.mean()


def form_residuals(X: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
                   angles: np.ndarray, hinge: tuple[np.ndarray, np.ndarray] | None = None,
                   ) -> dict[str, Any]:
    """How far the forms of ``X`` (n, 3) are from target forms.

    Returns summaries (:func:`solver.mesh.metrics.summary`: mean, rms, max, p95 of absolute
    values) of the relative length error ``l/L - 1`` over every edge (``length_error``), of
    the dihedral-angle error in radians over interior edges (``angle_error``), and
    ``length_ratio`` = mean of ``l/L``. For a planar ``X`` (n, 2) the angle error is 0.
    ``hinge``: :func:`hinges` of ``topology``, when the caller has them.
    """
    _, current = edge_vectors(X, topology.edges)
    out: dict[str, Any] = {"length_error": summary(current / lengths - 1.0),
                           "length_ratio": float(np.mean(current / lengths))
                           if len(lengths) else 1.0}
    if X.shape[1] == 3:
        inner, hinge = hinge if hinge is not None else hinges(topology)
        theta, _ = hinge_angles(X, hinge, gradients=False)
        out["angle_error"] = summary(wrap_angle(theta - angles[inner]))
    else:
        out["angle_error"] = summary(np.zeros(0))
    return out


def well_shaped_errors(X: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
                       angles: np.ndarray, energy: FormEnergy | None = None) -> float:
    """The largest form error of ``X`` (n, 3) on the well-shaped elements: the largest
    relative length error plus the largest dihedral-angle error (rad) over the edges of no
    cap face (:func:`cap_faces`: needles, slivers, near-zero-area faces). ``energy``: the
    :class:`FormEnergy` of these targets, whose caps and hinges are reused when given.

    Example:
        >>> import numpy as np
        >>> from solver.mesh.topology import build_topology
        >>> topo = build_topology(np.array([[0, 1, 2], [0, 2, 3]]))
        >>> V = np.array([[0., 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
        >>> L = np.linalg.norm(V[topo.edges[:, 1]] - V[topo.edges[:, 0]], axis=1)
        >>> well_shaped_errors(V, topo, L, np.zeros(5)), well_shaped_errors(V, topo, L * 1.1,
        ...                                                                np.zeros(5)) > 0.09
        (0.0, True)
    """
    known = energy is not None and energy.caps is not None
    keep = ~(energy.caps if known else cap_faces(topology, lengths)).is_cap_edge
    _, current = edge_vectors(X, topology.edges)
    length_error = np.abs(current[keep] / lengths[keep] - 1.0).max(initial=0.0)
    inner, hinge = energy.hinges if known else hinges(topology)
    theta, _ = hinge_angles(X, hinge, gradients=False)
    angle_error = np.abs(wrap_angle(theta - angles[inner]))[keep[inner]].max(initial=0.0)
    return float(length_error + angle_error)


def reproduces(X: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
               angles: np.ndarray, hinge: tuple[np.ndarray, np.ndarray] | None = None) -> bool:
    """Whether ``X`` (n, 3) or (n, 2) has the target forms: every relative length error and
    angle error (rad) within :data:`FORMS_TOLERANCE` (then there is nothing to refine).
    ``hinge`` as in :func:`form_residuals`."""
    _, current = edge_vectors(X, topology.edges)
    if np.abs(current / lengths - 1.0).max(initial=0.0) > FORMS_TOLERANCE:
        return False  # the usual answer, without the angles
    residual = form_residuals(X, topology, lengths, angles, hinge)
    return bool(max(residual["length_error"]["max"], residual["angle_error"]["max"])
                <= FORMS_TOLERANCE)



# ------------------------------------------------------------------------ the residuals

Evaluate = Callable[..., tuple[np.ndarray, np.ndarray | None]]
"""``evaluate(X, grad=True) -> (r (rows,), G (rows, q, dim) or None)``: the weighted
residuals of a group at positions ``X`` (n, dim) and their gradients with respect to the
``q`` vertices of each row."""


Curvature = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``curvature(X, r) -> (rows (k,) int64, M (k, dim, dim))``: for residuals of two vertices
that depend on ``x_1 - x_0`` only, the part ``r ∇²r`` of the Hessian of ``r^2 / 2`` that the
Gauss-Newton matrix keeps for some rows: ``+M`` on the blocks (0, 0) and (1, 1), ``-M`` on
(0, 1) (:mod:`solver.refine.normal_equations`)."""


@dataclass
class ResidualGroup:
    """One kind of residual: ``rows`` residuals, each touching ``q`` vertices.

    Attributes:
        vertices: (rows, q) int64 the vertices of each residual.
        evaluate: :data:`Evaluate`.
        hinge: whether the rows are hinges ``[i, j, a, b]`` (their pairs other than
            ``(a, b)`` are edges, present in the length group).
        curvature: optional :data:`Curvature` (q = 2 only).
    """

    vertices: np.ndarray
    evaluate: Evaluate
    hinge: bool = False
    curvature: Curvature | None = None


class FormEnergy:
    """The weighted residuals of :math:`E` for targets and handles, and E itself.

    Args:
        targets: :class:`FormTargets`.
        handles: :class:`Handles`; their target values may change
            (:meth:`set_handle_targets`).
        dim: 3, or 2 for a planar fit.

    Attributes:
        groups: list of :class:`ResidualGroup`.
        free: (n,) bool, the vertices that move (not fixed, referenced by a face).
        held: (n,) bool, the vertices a handle holds (fixed, soft, or in an orientation
            handle's face): E is invariant under the rigid motions of a connected
            component without any (:mod:`solver.mesh.rigid_motions`).
        hinges: :func:`hinges` of the topology (dim 3), else None.
        caps: :func:`cap_faces` of the targets (dim 3), else None; where the angles weigh
            (``angle_weight > 0``) their edges' angles are replaced by the apex residual.
        scale: ``s``, the mean target length.
        needle_vertices: (k,) int64 the vertices of needle edges, whose length residual's
            stiffness ``w / L^2`` is at least :data:`NEEDLE_STIFFNESS` times a mean edge's
            ``1 / s^2`` (shorter than a hundredth of the mean, uniformly weighted).
    """

    def __init__(self, targets: FormTargets, handles: Handles, dim: int) -> None:
        topo = targets.topology
        self.topology = topo
        self.dim = dim
        self.n = topo.n_vertices
        self.scale = float(np.mean(targets.lengths))
        self.groups: list[ResidualGroup] = []
        self.free = np.ones(self.n, dtype=bool)
        self.free[handles.fixed] = False
        self.free &= topo.is_referenced
        self.held = np.zeros(self.n, dtype=bool)
        self.held[handles.fixed] = True
        self.held[handles.soft_vertices] = True
        self.held[topo.faces[handles.frame_faces].ravel()] = True
        self.ties = (needle_ties(topo, targets.lengths, self.held) if dim == 3
                     else no_ties())
        self.free[self.ties.vertices] = False
        self.tie_offsets: np.ndarray | None = None
        if targets.weighting == "area":
            length_weights, hinge_weights = form_weights(topo, targets.lengths)
        else:
            length_weights = hinge_weights = np.ones(topo.n_edges)
        # An edge within a tie cluster keeps its length by the tie: it leaves the energy
        # (its residual, constant in every step, would only add rounding to the matrix).
        rigid = self.ties.rigid_edges(topo.edges, self.n)
        self._add_lengths(topo.edges, targets.lengths, np.where(rigid, 0.0, length_weights))
        self.hinges = hinges(topo) if dim == 3 else None
        self.caps = cap_faces(topo, targets.lengths) if dim == 3 else None
        if dim == 3 and targets.angle_weight > 0:
            inner, hinge = self.hinges
            kept = ~self.caps.is_cap_edge[inner]
            inner, hinge = inner[kept], hinge[kept]
            self._add_hinges(hinge, targets.angles[inner],
                             targets.angle_weight * hinge_weights[inner])
            if len(self.caps.faces):
                self._add_caps(self.caps, length_weights)
        if dim == 2 and targets.area_weight > 0:
            self._add_areas(topo, targets.lengths, targets.area_weight)
        if len(handles.soft_vertices):
            self._add_soft_positions(handles)
        if len(handles.frame_faces):
            self._add_frames(topo.faces, handles)

    def tie(self, X: np.ndarray) -> None:
        """Set the offsets of the tied vertices (:mod:`solver.refine.ties`) from a run's start
        positions ``X`` (n, dim) and place them there (in place)."""
        if len(self.ties):
            self.tie_offsets = self.ties.offsets(X)
            self.ties.place(X, self.tie_offsets)

    def place_tied(self, X: np.ndarray) -> None:
        """Put the tied vertices of ``X`` (n, dim) at their masters plus the offsets of the
        last :meth:`tie` (in place: a step moves the masters only)."""
        if len(self.ties) and self.tie_offsets is not None:
            self.ties.place(X, self.tie_offsets)

    def placed(self, X: np.ndarray, own: bool = False) -> np.ndarray:
        """``X`` (n, dim), or a copy with its tied vertices placed: at the offsets of the
        last :meth:`tie`, or with ``own`` (or before any) at those ``X`` itself gives (its
        needles put on their target lengths, as a run starting at ``X`` does)."""
        if not len(self.ties):
            return X
        offsets = self.ties.offsets(X) if own or self.tie_offsets is None \
            else self.tie_offsets
        X = X.copy()
        self.ties.place(X, offsets)
        return X

    def set_handle_targets(self, soft_positions: np.ndarray | None = None,
                           frame_edges: np.ndarray | None = None) -> None:
        """Replace the soft handle positions (p, dim) and the orientation handles' target
        edge vectors (q, 2, dim) (``None`` keeps the current ones)."""
        if soft_positions is not None:
            self.soft_positions = np.asarray(soft_positions, dtype=np.float64)
        if frame_edges is not None:
            self.frame_edges = np.asarray(frame_edges, dtype=np.float64)

    def energy(self, X: np.ndarray) -> float:
        """E (see the module docstring) of positions ``X`` (n, dim), its tied vertices
        placed (:meth:`placed`; ``X`` is not changed)."""
        X = self.placed(X)
        return 0.5 * sum(square_sum(g.evaluate(X, False)[0]) for g in self.groups)

    # -- residual groups (each returns weighted residuals and their gradients)

    def _add_lengths(self, edges: np.ndarray, L: np.ndarray, weights: np.ndarray) -> None:
        w = np.sqrt(weights)
        stiff = STRETCH_CURVATURE / self.scale**2
        needles = weights / L**2 >= NEEDLE_STIFFNESS / self.scale**2
        self.needle_vertices = np.unique(edges[needles].ravel())

        def evaluate(X: np.ndarray, grad: bool = True):
            d, length = edge_vectors(X, edges)
            r = w * (length / L - 1.0)
            if not grad:
                return r, None
            unit = d * (w / (np.where(length > 0, length, 1.0) * L))
            G = np.empty((len(r), 2, X.shape[1]))
            G[:, 1] = unit.T
            np.negative(G[:, 1], out=G[:, 0])
            return r, G

        def curvature(X: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            # r ∇²r = w² (l/L - 1) / (L l) (I - u u^T) across a stretched edge (l from r);
            # kept where it is at least STRETCH_CURVATURE x a mean edge's 1 / s^2.
            length = L * (1.0 + r / np.where(w > 0, w, 1.0))  # (w = 0: a tie's edge)
            c = np.maximum(r, 0.0) * w / (L * np.maximum(length, L))
            rows = np.flatnonzero(c >= stiff)
            d = X[edges[rows, 1]] - X[edges[rows, 0]]
            u = d / np.linalg.norm(d, axis=1)[:, None]
            M = np.eye(X.shape[1]) - u[:, :, None] * u[:, None, :]
            return rows, c[rows, None, None] * M

        self.groups.append(ResidualGroup(edges, evaluate, curvature=curvature))

    def _add_hinges(self, hinge: np.ndarray, target: np.ndarray, weights: np.ndarray) -> None:
        w = np.sqrt(weights)
        floor = DEGENERATE * self.scale**4

        def evaluate(X: np.ndarray, grad: bool = True):
            theta, G = hinge_angles(X, hinge, floor, grad)
            r = w * wrap_angle(theta - target)
            return r, (None if G is None else w[:, None, None] * G)

        self.groups.append(ResidualGroup(hinge, evaluate, hinge=True))

    def _add_caps(self, caps: CapFaces, length_weights: np.ndarray) -> None:
        # x_c - (1 - t) x_a - t x_b over the base's length: one row per coordinate.
        dim = self.dim
        coefficients = np.sqrt(length_weights[caps.edges[:, 0]])[:, None] * caps.coefficients
        G = coefficients[:, None, :, None] * np.eye(dim)[None, :, None, :]  # (k, dim, 3, dim)
        G = G.reshape(-1, 3, dim)

        def evaluate(X: np.ndarray, grad: bool = True):
            r = np.einsum("kc,kcd->kd", coefficients, X[caps.corners])
            return r.ravel(), (G if grad else None)

        self.groups.append(ResidualGroup(np.repeat(caps.corners, dim, axis=0), evaluate))

    def _add_areas(self, topo: MeshTopology, L: np.ndarray, weight: float) -> None:
        from ..mesh.frames import face_edge_lengths, triangle_areas

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

        self.groups.append(ResidualGroup(faces, evaluate))

    def _add_soft_positions(self, h: Handles) -> None:
        w = np.sqrt(h.soft_weights) / self.scale
        eye = np.broadcast_to(np.eye(self.dim), (len(w), self.dim, self.dim))
        G = (w[:, None, None] * eye).reshape(-1, 1, self.dim)
        self.soft_positions = np.array(h.soft_positions, dtype=np.float64)

        # One residual per coordinate: rows (p * dim,), each touching one vertex.
        def evaluate(X: np.ndarray, grad: bool = True):
            r = (w[:, None] * (X[h.soft_vertices] - self.soft_positions)).ravel()
            return r, (G if grad else None)

        self.groups.append(ResidualGroup(np.repeat(h.soft_vertices[:, None], self.dim, axis=0),
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

        self.groups.append(ResidualGroup(np.repeat(pairs, dim, axis=0), evaluate))


def square_sum(r: np.ndarray) -> float:
    """``r . r`` of a residual vector, without BLAS: numpy's ``dot`` hands long vectors to
    a multithreaded BLAS, whose threads cost ~20 ms per call on a loaded machine (measured
    at load 7-10 on 2 cores: 8 dot products of 30K entries took 170 ms, ``einsum`` 0.2 ms;
    ``python -m bench.blas_threads``)."""
    return float(np.einsum("i,i->", r, r))
