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

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..mesh.embedding_geometry import edge_vectors, hinge_angles, hinges
from ..mesh.metrics import summary, wrap_angle
from ..mesh.topology import MeshTopology
from .energy_weights import ANGLE_WEIGHT, AREA_WEIGHT
from .residual_groups import (  # noqa: F401 - re-exported: the energy's public names
    DEGENERATE,
    NEEDLE_STIFFNESS,
    STRETCH_CURVATURE,
    AreaResiduals,
    CapResiduals,
    Curvature,
    Evaluate,
    FrameResiduals,
    HingeResiduals,
    LengthResiduals,
    ResidualGroup,
    SoftPositionResiduals,
    square_sum,
)
from .ties import Ties, needle_ties, no_ties

FORMS_TOLERANCE = 1e-9
"""Largest relative length error and angle error (rad) of an embedding that "has" the forms:
then there is nothing to refine."""
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
    safe = np.where(longest > 0, longest, 1.0)
    # Screen with 16 A^2 / longest^4 from the squared lengths (no sort; its rounding, ~1e-15,
    # is far below the threshold's 4 CAP_HEIGHT^2): a cap has it under 4 CAP_HEIGHT^2, so
    # faces under 4 times that are measured by the stable formula (a row of a blend asks).
    q = (face_lengths / safe[:, None]) ** 2
    area16 = 2.0 * (q[:, 0] * q[:, 1] + q[:, 1] * q[:, 2] + q[:, 2] * q[:, 0]) - (
        q[:, 0] ** 2 + q[:, 1] ** 2 + q[:, 2] ** 2)
    suspects = np.flatnonzero((area16 < 16.0 * CAP_HEIGHT**2) & (longest > 0))
    height = 2.0 * triangle_areas(face_lengths[suspects]) / longest[suspects]
    faces = suspects[height < CAP_HEIGHT * longest[suspects]]
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


class FormEnergy:
    """The weighted residuals of :math:`E` for targets and handles, and E itself.

    Built once per connectivity, handles and *structure* of the targets (their needle ties
    and cap faces, which the target lengths decide); :meth:`retarget` replaces the targets'
    values (lengths, angles, weights) in place where the structure is the same, so the
    groups' vertex rows, and the Gauss-Newton pattern built on them, stay
    (:meth:`solver.refine.Refiner.retarget`).

    Args:
        targets: :class:`FormTargets`.
        handles: :class:`Handles`; their target values may change
            (:meth:`set_handle_targets`).
        dim: 3, or 2 for a planar fit.

    Attributes:
        groups: list of :class:`~solver.refine.residual_groups.ResidualGroup`, the lengths'
            first.
        free: (n,) bool, the vertices that move (not fixed, referenced by a face).
        held: (n,) bool, the vertices a handle holds (fixed, soft, or in an orientation
            handle's face): E is invariant under the rigid motions of a connected
            component without any (:mod:`solver.mesh.rigid_motions`).
        hinges: :func:`hinges` of the topology (dim 3), else None.
        caps: :func:`cap_faces` of the targets (dim 3), else None; where the angles weigh
            (``angle_weight > 0``) their edges' angles are replaced by the apex residual.
        ties: :class:`~solver.refine.ties.Ties` of the targets' needle edges (dim 3).
        scale: ``s``, the mean target length.
        needle_vertices: (k,) int64 the vertices of needle edges, whose length residual's
            stiffness ``w / L^2`` is at least :data:`NEEDLE_STIFFNESS` times a mean edge's
            ``1 / s^2`` (shorter than a hundredth of the mean, uniformly weighted).
    """

    def __init__(self, targets: FormTargets, handles: Handles, dim: int) -> None:
        topo = targets.topology
        self.topology, self.dim, self.n = topo, dim, topo.n_vertices
        self.free = np.ones(self.n, dtype=bool)
        self.free[handles.fixed] = False
        self.free &= topo.is_referenced
        self.held = np.zeros(self.n, dtype=bool)
        self.held[handles.fixed] = True
        self.held[handles.soft_vertices] = True
        self.held[topo.faces[handles.frame_faces].ravel()] = True
        self.ties, self.caps = self._structure(targets)
        self.free[self.ties.vertices] = False
        self.tie_offsets: np.ndarray | None = None
        self.hinges = hinges(topo) if dim == 3 else None
        self._seen: dict[str, tuple[np.ndarray, list[np.ndarray]]] = {}
        self._build_groups(targets, handles)
        self._set_values(targets)

    def _structure(self, targets: FormTargets) -> tuple[Ties, CapFaces | None]:
        """The needle ties and cap faces (dim 3) that ``targets``' lengths give."""
        if self.dim != 3:
            return no_ties(), None
        topo = targets.topology
        return needle_ties(topo, targets.lengths, self.held), cap_faces(topo, targets.lengths)

    def _weighs(self, targets: FormTargets) -> tuple[bool, bool]:
        """Whether the angles and the areas enter E (which groups there are)."""
        return (self.dim == 3 and targets.angle_weight > 0,
                self.dim == 2 and targets.area_weight > 0)

    def _build_groups(self, targets: FormTargets, handles: Handles) -> None:
        """The residual groups' structure (vertex rows): lengths (every edge), hinges and
        cap faces (dim 3, angles weighed), areas (dim 2), soft and orientation handles."""
        topo, dim = self.topology, self.dim
        self.weighs = self._weighs(targets)
        self.length_group = LengthResiduals(topo.edges)
        self.groups: list[ResidualGroup] = [self.length_group]
        self.hinge_group: HingeResiduals | None = None
        self.cap_group: CapResiduals | None = None
        self.area_group: AreaResiduals | None = None
        if self.weighs[0]:
            inner, hinge = self.hinges
            self.kept_hinges = ~self.caps.is_cap_edge[inner]
            self.hinge_group = HingeResiduals(hinge[self.kept_hinges])
            self.groups.append(self.hinge_group)
            if len(self.caps.faces):
                self.cap_group = CapResiduals(self.caps.corners, dim)
                self.groups.append(self.cap_group)
        if self.weighs[1]:
            self.area_group = AreaResiduals(topo.faces)
            self.groups.append(self.area_group)
        self.soft_group = self.frame_group = None
        if len(handles.soft_vertices):
            self.soft_group = SoftPositionResiduals(handles.soft_vertices,
                                                    handles.soft_weights,
                                                    handles.soft_positions, dim)
            self.groups.append(self.soft_group)
        if len(handles.frame_faces):
            self.frame_group = FrameResiduals(topo.faces[handles.frame_faces],
                                              handles.frame_weights, handles.frame_edges, dim)
            self.groups.append(self.frame_group)

    def _set_values(self, targets: FormTargets) -> None:
        """Every group's values from ``targets`` (whose structure is this energy's)."""
        from ..mesh.frames import face_edge_lengths, triangle_areas

        topo, L = self.topology, targets.lengths
        self.targets = targets
        self.scale = scale = float(np.mean(L))
        if targets.weighting == "area":
            length_weights, hinge_weights = form_weights(topo, L)
        else:
            length_weights = hinge_weights = np.ones(topo.n_edges)
        # An edge within a tie cluster keeps its length by the tie: it leaves the energy
        # (its residual, constant in every step, would only add rounding to the matrix).
        rigid = self.ties.rigid_edges(topo.edges, self.n)
        self.length_group.set(L, np.where(rigid, 0.0, length_weights), scale)
        self.needle_vertices = self.length_group.needle_vertices
        if self.hinge_group is not None:
            inner = self.hinges[0][self.kept_hinges]
            self.hinge_group.set(targets.angles[inner],
                                 targets.angle_weight * hinge_weights[inner], scale)
        if self.cap_group is not None:
            caps = self.caps
            self.cap_group.set(np.sqrt(length_weights[caps.edges[:, 0]])[:, None]
                               * caps.coefficients)
        if self.area_group is not None:
            self.area_group.set(triangle_areas(face_edge_lengths(topo, L)),
                                targets.area_weight, scale)
        for group in (self.soft_group, self.frame_group):
            if group is not None:
                group.set(scale)
        self._seen.clear()

    def retarget(self, targets: FormTargets) -> bool:
        """Replace the targets' values (lengths, angles, weights) in place. Returns False,
        changing nothing, where ``targets`` have another structure: another topology,
        other needle ties or cap faces (:func:`cap_faces`), or angles or areas that weigh
        where these do not (or the reverse)."""
        topo = targets.topology
        if topo is not self.topology and not (
                topo.n_vertices == self.n and topo.faces.shape == self.topology.faces.shape
                and np.array_equal(topo.faces, self.topology.faces)):
            return False
        if self._weighs(targets) != self.weighs:
            return False
        ties, caps = self._structure(targets)
        if not (_same_ties(ties, self.ties) and _same_caps(caps, self.caps)):
            return False
        self.ties, self.caps = ties, caps
        self._set_values(targets)
        return True

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
        if soft_positions is not None and self.soft_group is not None:
            self.soft_group.positions = np.asarray(soft_positions, dtype=np.float64)
            self._seen.clear()
        if frame_edges is not None and self.frame_group is not None:
            self.frame_group.frame_edges = np.asarray(frame_edges, dtype=np.float64)
            self._seen.clear()

    def energy(self, X: np.ndarray) -> float:
        """E (see the module docstring) of positions ``X`` (n, dim), its tied vertices
        placed (:meth:`placed`; ``X`` is not changed). The residuals are remembered for
        :meth:`report` of this ``X`` (the same object, not changed since)."""
        placed = self.placed(X)
        residuals = [g.evaluate(placed, False)[0] for g in self.groups]
        self.remember(X, residuals, "energy")
        return 0.5 * sum(square_sum(r) for r in residuals)

    def remember(self, X: np.ndarray, residuals: list[np.ndarray], slot: str) -> None:
        """Keep each group's residuals at ``X`` (n, dim) for :meth:`report`: the last of
        each ``slot`` (``"energy"``: :meth:`energy`'s; ``"point"``: the Gauss-Newton
        system's, at an iteration's point). Callers never change ``X`` in place
        afterwards (the refinement's iterates are new arrays)."""
        self._seen[slot] = (X, residuals)

    def report(self, X: np.ndarray) -> dict[str, Any]:
        """:func:`form_residuals` of ``X`` (n, dim) against the targets (to round-off), from
        the residuals :meth:`energy` or the Gauss-Newton system last computed at this very
        array, else from one evaluation of the groups: no second pass of the forms over the
        mesh. The edges a tie holds rigid and the hinges of cap faces, which E leaves out,
        are measured on their own."""
        residuals = next((seen for at, seen in self._seen.values() if at is X), None)
        placed = self.placed(X)
        if residuals is None:
            residuals = [g.evaluate(placed, False)[0] for g in self.groups]
        length_error = self.length_group.errors(residuals[0], placed)
        out: dict[str, Any] = {"length_error": summary(length_error),
                               "length_ratio": float(np.mean(length_error + 1.0))
                               if len(length_error) else 1.0}
        out["angle_error"] = summary(self._angle_errors(placed, residuals))
        return out

    def _angle_errors(self, X: np.ndarray, residuals: list[np.ndarray]) -> np.ndarray:
        """Dihedral-angle errors (interior edges,) of ``X`` whose residuals are given:
        from the hinge group's, the hinges E leaves out measured on ``X`` (empty in 2D)."""
        if self.dim != 3:
            return np.zeros(0)
        inner, hinge = self.hinges
        angles = self.targets.angles
        if self.hinge_group is None:
            theta, _ = hinge_angles(X, hinge, gradients=False)
            return wrap_angle(theta - angles[inner])
        errors = np.empty(len(inner))
        kept = self.kept_hinges
        errors[kept] = self.hinge_group.errors(residuals[1])
        if not kept.all():
            theta, _ = hinge_angles(X, hinge[~kept], gradients=False)
            errors[~kept] = wrap_angle(theta - angles[inner[~kept]])
        return errors


def _same_ties(a: Ties, b: Ties) -> bool:
    """Whether two ties join the same vertices to the same masters by the same edges."""
    return all(np.array_equal(x, y) for x, y in ((a.vertices, b.vertices),
                                                 (a.masters, b.masters), (a.edges, b.edges)))


def _same_caps(a: CapFaces | None, b: CapFaces | None) -> bool:
    """Whether two sets of cap faces have the same faces, bases and apexes."""
    if a is None or b is None:
        return a is b
    return np.array_equal(a.faces, b.faces) and np.array_equal(a.corners, b.corners)
