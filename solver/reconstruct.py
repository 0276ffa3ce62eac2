"""Vertex positions from discrete fundamental forms: one sparse linear solve (Sec. 3-4).

:class:`ImmersionProblem` holds the assembled energy of Eq. (5) for a set of forms;
:func:`reconstruct` adds constraints (or anchors), factorizes once and solves for the three
coordinates; with ``orthonormalize=True`` it projects the frames to rotations and solves again
with them as soft constraints (Sec. 4). :class:`solver.deform.Deformer` reuses the same pieces.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from .constraints import Constraints
from .errors import ConstraintError, TriangleInequalityError
from .form_energy import well_shaped_errors
from .forms import flat_faces, validate_forms, wrapped_angle_count
from .frames import (
    face_edge_lengths,
    layout_frames,
    triangle_inequality_error,
    triangle_inequality_violations,
)
from .integrability import (
    integrability_from_terms,
    integrate_along_forests,
    integration_forests,
)
from .layout_fit import LayoutFit
from .linalg import resolve_backend
from .manifold import ManifoldCut
from .options import COTAN_FLOOR, FRAME_WEIGHT, ReconstructOptions
from .outcomes import not_refined
from .placement import Placement, apply_placement, side_by_side
from .refine import HARD_FRAME_WEIGHT, FormTargets, Handles, Refiner, reproduces
from .reports import Progress, ReconstructReport, Stages
from .rotations import nearest_rotation
from .serialization import JsonDataclass
from .system import (
    WEIGHTINGS,
    ConstrainedSystem,
    EnergyTerms,
    LinearConstraints,
    Weighting,
    energies,
    energy_terms,
    frame_columns,
    least_squares_rows,
    max_weighted_residual,
    normal_matrix,
    unknown_groups,
)
from .topology import MeshTopology
from .validation import as_points
from .warnings import as_report, refinement_warnings

REGULARIZATION = 1e-6
EXACT_TOLERANCE = 1e-10  # residual rows (normalized lengths) accepted without a solve


@dataclass
class Reconstruction(JsonDataclass):
    """Result of :func:`reconstruct`.

    Attributes:
        vertices: (n, 3) float64 positions.
        frames: (m, 3, 3) float64 face frames of the last solve (columns b1, b2, b3).
        report: :class:`solver.reports.ReconstructReport` (energies, timings per stage,
            backend, anchors, integrability).
    """

    vertices: np.ndarray
    frames: np.ndarray
    report: ReconstructReport

    _array_fields: ClassVar[dict[str, Any]] = {"vertices": np.float64, "frames": np.float64}
    _nested_fields: ClassVar[dict[str, Any]] = {"report": ReconstructReport}


class ImmersionProblem:
    """The energy of Eq. (5) for one set of forms, in units of ``length_scale``.

    Attributes:
        terms: layouts, coefficients, rotations, weights.
        A, row_weights, row_kind: the residual operator (see :mod:`solver.system`).
        K: (N, N) normal matrix, N = n + 3 m (assembled lazily).
        length_scale: lengths were divided by it; solutions are multiplied back.
    """

    def __init__(self, topology: MeshTopology, lengths: np.ndarray, angles: np.ndarray, *,
                 frame_weight: float = FRAME_WEIGHT, weighting: Weighting = "uniform",
                 cotan_floor: float = COTAN_FLOOR, length_scale: float | None = None,
                 layout_angles: np.ndarray | None = None) -> None:
        if weighting not in WEIGHTINGS:
            raise ConstraintError(f"unknown weighting {weighting!r}; use one of {WEIGHTINGS}",
                                  field="options.weighting")
        if not frame_weight > 0 or not np.isfinite(frame_weight):
            raise ConstraintError(f"frame_weight must be positive and finite, got {frame_weight}",
                                  field="options.frame_weight")
        self.topology = topology
        self.lengths, self.angles = lengths, angles  # (E,) as given (input units)
        self.length_scale = float(lengths.mean()) if length_scale is None else float(length_scale)
        self.frame_weight = float(frame_weight)
        self.weighting = weighting
        try:
            self.terms: EnergyTerms = energy_terms(
                topology, lengths / self.length_scale, angles, weighting=weighting,
                cotan_floor=cotan_floor, layout_angles=layout_angles)
        except TriangleInequalityError:  # it saw normalized lengths: quote the caller's
            bad = triangle_inequality_violations(face_edge_lengths(topology, lengths))
            if not len(bad):
                raise
            raise triangle_inequality_error(topology, lengths, bad) from None
        self.A, self.row_weights, self.row_kind = least_squares_rows(self.terms, frame_weight)
        self._residual: tuple[np.ndarray, np.ndarray] | None = None  # (u, A @ u), once

    @functools.cached_property
    def K(self) -> sp.csc_matrix:  # noqa: N802 - the matrix of the paper
        """(N, N) normal matrix A^T W A, assembled on first use (the tree-integration
        shortcut never needs it)."""
        return normal_matrix(self.A, self.row_weights)

    @property
    def n_unknowns(self) -> int:
        return self.terms.n_unknowns

    def unknowns_to_geometry(self, u: np.ndarray, constraints: Constraints | None = None,
                             ) -> tuple[np.ndarray, np.ndarray]:
        """Split (N, 3) unknowns into vertices (n, 3) (in input units) and frames (m, 3, 3).

        Hard position constraints are copied to the output bit for bit (undoing the length
        normalization would otherwise round them).
        """
        n = self.topology.n_vertices
        frames = np.swapaxes(u[n:].reshape(-1, 3, 3), 1, 2)  # u[n + 3t + c, k] = f_t[k, c]
        vertices = u[:n] * self.length_scale
        if constraints is not None:
            hard = np.isinf(constraints.position_weights)
            vertices[constraints.position_vertices[hard]] = constraints.positions[hard]
        return vertices, frames

    def energies(self, u: np.ndarray) -> dict[str, float]:
        """Residual energy per term (in normalized units) of unknowns u (N, 3)."""
        kept = self._residual
        residual = kept[1] if kept is not None and kept[0] is u else None
        self._residual = None
        return energies(self.A, self.row_weights, self.row_kind, u, residual)

    def linear_constraints(self, constraints: Constraints) -> LinearConstraints:
        """Map validated user constraints to unknown columns (positions scaled)."""
        n = self.topology.n_vertices
        pos_hard = np.isinf(constraints.position_weights)
        frm_hard = np.isinf(constraints.frame_weights)
        f_cols = frame_columns(n, constraints.frame_faces)             # (q, 3) cols f_t[k, c]
        f_vals = np.swapaxes(constraints.frames, 1, 2)                 # [t, c, k] = f_t[k, c]
        return LinearConstraints(
            hard_columns=np.concatenate([constraints.position_vertices[pos_hard],
                                         f_cols[frm_hard].ravel()]),
            hard_values=np.concatenate([constraints.positions[pos_hard] / self.length_scale,
                                        f_vals[frm_hard].reshape(-1, 3)]),
            soft_columns=np.concatenate([constraints.position_vertices[~pos_hard],
                                         f_cols[~frm_hard].ravel()]),
            soft_values=np.concatenate([constraints.positions[~pos_hard] / self.length_scale,
                                        f_vals[~frm_hard].reshape(-1, 3)]),
            soft_weights=np.concatenate([constraints.position_weights[~pos_hard],
                                         np.repeat(constraints.frame_weights[~frm_hard], 3)]),
        )

    def constrained_components(self, constraints: Constraints) -> np.ndarray:
        """(C,) bool: components touched by at least one constraint."""
        topo = self.topology
        touched = np.zeros(topo.n_components, dtype=bool)
        touched[topo.vertex_component[constraints.position_vertices]] = True
        touched[topo.face_component[constraints.frame_faces]] = True
        return touched

    def anchors(self, components: np.ndarray, reference_vertices: np.ndarray | None = None,
                reference_frames: np.ndarray | None = None,
                ) -> tuple[LinearConstraints, list[dict[str, int]]]:
        """Hard anchors for the components where ``components`` (C,) bool is True.

        Each gets its first face's first vertex at the origin and that face's frame at the
        identity (Sec. 3: "after fixing one vertex and one frame, the system becomes
        positive-definite"), or at their reference values when given (reference vertices
        in input units); unused vertices are pinned at the origin (or reference).
        """
        topo = self.topology
        face_comps, first_face = np.unique(topo.face_component, return_index=True)
        chosen = components[face_comps]
        faces = first_face[chosen]
        vertices = topo.faces[faces, 0]
        pinned = np.concatenate([vertices, topo.isolated_vertices]).astype(np.int64)
        cols = np.concatenate([pinned, frame_columns(topo.n_vertices, faces).ravel()])
        if reference_vertices is None or reference_frames is None:
            values = np.concatenate([np.zeros((len(pinned), 3)),
                                     np.tile(np.eye(3), (len(faces), 1))])
        else:
            values = np.concatenate([reference_vertices[pinned] / self.length_scale,
                                     np.swapaxes(reference_frames[faces], 1, 2).reshape(-1, 3)])
        info = [{"component": int(c), "vertex": int(v), "face": int(t)}
                for c, v, t in zip(face_comps[chosen], vertices, faces, strict=True)]
        return LinearConstraints(hard_columns=cols, hard_values=values), info

    def underdetermined_components(self, constraints: Constraints,
                                   reference_vertices: np.ndarray | None = None,
                                   ) -> tuple[np.ndarray, np.ndarray]:
        """Components constrained by positions only, and by frames only.

        The linear energy of exact forms is invariant under every affine map of (x, f), so
        position constraints alone fix a component only when their points span 3D (four or
        more, not coplanar); with a reference embedding, position-only components whose
        constrained reference points do span 3D are not listed. With frames only,
        translation is free.
        """
        topo = self.topology
        has_pos = np.zeros(topo.n_components, dtype=bool)
        has_frm = np.zeros(topo.n_components, dtype=bool)
        has_pos[topo.vertex_component[constraints.position_vertices]] = True
        has_frm[topo.face_component[constraints.frame_faces]] = True
        position_only = has_pos & ~has_frm
        if reference_vertices is not None:
            position_only &= ~self._constraints_span_space(constraints, reference_vertices)
        return np.flatnonzero(position_only), np.flatnonzero(has_frm & ~has_pos)

    def _constraints_span_space(self, constraints: Constraints,
                                reference_vertices: np.ndarray) -> np.ndarray:
        """(C,) bool: the constrained reference points of each component span 3D."""
        C = self.topology.n_components
        comp = self.topology.vertex_component[constraints.position_vertices]
        points = reference_vertices[constraints.position_vertices]
        count = np.bincount(comp, minlength=C).astype(np.float64)
        safe = np.maximum(count, 1.0)[:, None]
        mean = np.stack([np.bincount(comp, points[:, k], C) for k in range(3)], 1) / safe
        centred = points - mean[comp]
        outer = centred[:, :, None] * centred[:, None, :]
        cov = np.stack([np.bincount(comp, outer[:, i, j], C) for i in range(3)
                        for j in range(3)], 1).reshape(C, 3, 3)
        eig = np.linalg.eigvalsh(cov)
        return (count >= 4) & (eig[:, 0] > 1e-8 * np.maximum(eig[:, 2], np.finfo(float).tiny))

    def gauge_constraints(self, constraints: Constraints, reference_vertices: np.ndarray,
                          reference_frames: np.ndarray, weight: float = REGULARIZATION,
                          ) -> tuple[LinearConstraints, list[int]]:
        """Fix the gauge that the user's constraints leave free, from a reference embedding.

        * Position-only components whose handles do not span 3D: the frames are pulled
          towards the reference frames with a soft weight of ``weight`` times the mean
          diagonal of the frame block of K (relative, so the conditioning stays ~1/weight).
        * Frame-only components: only translation is free; one vertex is pinned at its
          reference position and :meth:`recenter` later moves the component so its centroid
          matches the reference (translation is an exact null direction, so this is exact).

        Returns (constraints, sorted list of the components concerned).
        """
        topo = self.topology
        pos_only, frame_only = self.underdetermined_components(constraints, reference_vertices)
        faces = np.flatnonzero(np.isin(topo.face_component, pos_only))
        pinned = self._first_vertices(frame_only)
        n = topo.n_vertices
        weight = weight * float(self.K.diagonal()[n:].mean())
        gauge = LinearConstraints(
            hard_columns=pinned, hard_values=reference_vertices[pinned] / self.length_scale,
            soft_columns=frame_columns(topo.n_vertices, faces).ravel(),
            soft_values=np.swapaxes(reference_frames[faces], 1, 2).reshape(-1, 3),
            soft_weights=np.full(3 * len(faces), weight))
        return gauge, sorted(int(c) for c in np.concatenate([pos_only, frame_only]))

    def _first_vertices(self, components: np.ndarray) -> np.ndarray:
        """First vertex of the first face of each given component."""
        face_comps, first_face = np.unique(self.topology.face_component, return_index=True)
        return self.topology.faces[first_face[np.isin(face_comps, components)], 0]

    def recenter(self, vertices: np.ndarray, constraints: Constraints,
                 reference_vertices: np.ndarray) -> np.ndarray:
        """Translate frame-only components so their centroids match the reference."""
        topo = self.topology
        _, frame_only = self.underdetermined_components(constraints)
        if not len(frame_only):
            return vertices
        comp = topo.vertex_component
        moved = np.isin(comp, frame_only) & topo.is_referenced
        count = np.bincount(comp[moved], minlength=topo.n_components)
        shift = np.stack([np.bincount(comp[moved], weights=(reference_vertices - vertices)[
            moved, k], minlength=topo.n_components) for k in range(3)], axis=1)
        vertices = vertices.copy()
        vertices[moved] += shift[comp[moved]] / count[comp[moved], None]
        return vertices

    def integrated_solution(self, root_faces: ArrayLike, root_vertices: ArrayLike,
                            tol: float = EXACT_TOLERANCE) -> np.ndarray | None:
        """Unknowns (N, 3) integrated along spanning trees from the anchors (frame I at
        each root face, origin at each root vertex), or None if some weighted residual row
        of Eq. 5 exceeds ``tol`` (the forms are not integrable to that accuracy)."""
        forests = integration_forests(self.terms, np.asarray(root_faces, dtype=np.int64),
                                      np.asarray(root_vertices, dtype=np.int64))
        frames, _, positions = integrate_along_forests(self.terms, forests)
        if not np.isfinite(frames).all() or not np.isfinite(positions).all():
            return None
        u = np.concatenate([positions, np.swapaxes(frames, 1, 2).reshape(-1, 3)])
        residual = self.A @ u
        if max_weighted_residual(self.row_weights, residual) > tol:
            return None
        self._residual = (u, residual)  # energies(u) reuses it
        return u

    def system(self, constraints: LinearConstraints, backend: str = "auto",
               extra_penalty_columns: np.ndarray | None = None,
               extra_penalty_weight: float = 0.0,
               ordering_hint: bool = True) -> ConstrainedSystem:
        """Factorize K with ``constraints`` (and optional extra soft columns, e.g. every
        frame for the orthonormalization solve). ``ordering_hint``: pass the unknowns'
        groups to :func:`solver.linalg.factorize` (a cheaper analysis, slower solves); False
        for a system solved per drag."""
        soft_cols, soft_w = constraints.soft_columns, constraints.soft_weights
        if extra_penalty_columns is not None:
            soft_cols = np.concatenate([soft_cols, extra_penalty_columns])
            soft_w = np.concatenate([soft_w, np.full(len(extra_penalty_columns),
                                                     extra_penalty_weight)])
        topo = self.topology
        groups = unknown_groups(topo.n_vertices, topo.n_faces) if ordering_hint else None
        return ConstrainedSystem(self.K, constraints.hard_columns, soft_cols, soft_w, backend,
                                 groups)

    def refinement_handles(self, constraints: Constraints) -> Handles:
        """The user's constraints as :class:`solver.refine.Handles`: hard positions fixed,
        soft positions kept soft, frame constraints as target edge vectors (Eq. 3 with the
        constrained frame and the face's layout, in input units)."""
        hard = np.isinf(constraints.position_weights)
        frame_hard = np.isinf(constraints.frame_weights)
        layouts = self.terms.layouts[constraints.frame_faces] * self.length_scale  # (q, 3, 2)
        planar = np.stack([layouts[:, 1] - layouts[:, 0], layouts[:, 2] - layouts[:, 0]], 1)
        edges = np.einsum("qkc,qec->qek", constraints.frames[:, :, :2], planar)
        return Handles(
            fixed=constraints.position_vertices[hard],
            soft_vertices=constraints.position_vertices[~hard],
            soft_positions=constraints.positions[~hard],
            soft_weights=constraints.position_weights[~hard],
            frame_faces=constraints.frame_faces, frame_edges=edges,
            frame_weights=np.where(frame_hard, HARD_FRAME_WEIGHT, constraints.frame_weights))

    def layout_fit(self, constraints: Constraints, backend: str = "auto") -> LayoutFit:
        """The refinement's start (:class:`solver.layout_fit.LayoutFit`) for validated user
        constraints: hard positions fixed, soft ones pulled with their weights."""
        hard = np.isinf(constraints.position_weights)
        return LayoutFit(self.topology, self.terms.layouts * self.length_scale,
                         fixed=constraints.position_vertices[hard],
                         soft=constraints.position_vertices[~hard],
                         soft_weights=constraints.position_weights[~hard], backend=backend)

    def refinement_start(self, fit: LayoutFit, frames: np.ndarray, constraints: Constraints,
                         vertices: np.ndarray) -> np.ndarray:
        """Positions (n, 3) that best fit the layouts rotated by the rotations nearest to
        ``frames`` (m, 3, 3) (constrained faces by their constraint frames), with the
        constraints' positions and the pinned vertices where ``vertices`` (n, 3), the
        linear answer, has them: the start of the refinement."""
        rotations = nearest_rotation(frames)
        rotations[constraints.frame_faces] = constraints.frames
        hard = np.isinf(constraints.position_weights)
        return fit.solve(rotations, constraints.positions[hard], constraints.positions[~hard],
                         vertices[fit.pinned])

    def frames_of(self, vertices: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
        """(m, 3, 3) rotations nearest to the frames that map each face's layout onto
        ``vertices`` (n, 3) (input units); only of ``faces`` (k,) when given."""
        chosen = slice(None) if faces is None else faces
        frames = layout_frames(vertices / self.length_scale, self.topology.faces[chosen],
                               self.terms.layouts[chosen])
        return nearest_rotation(frames)

    def place_anchored(self, vertices: np.ndarray, anchored: list[dict[str, int]],
                       ) -> np.ndarray:
        """Move each anchored component rigidly so that its anchor vertex is at the origin
        and its anchor face's frame is the identity again (after a refinement, which keeps
        no anchor)."""
        if not anchored:
            return vertices
        comps = np.array([a["component"] for a in anchored], dtype=np.int64)
        faces = np.array([a["face"] for a in anchored], dtype=np.int64)
        origin = vertices[[a["vertex"] for a in anchored]]                # (c, 3)
        frames = self.frames_of(vertices, faces)                           # (c, 3, 3)
        slot = np.full(self.topology.n_components, -1, dtype=np.int64)
        slot[comps] = np.arange(len(comps))
        which = slot[self.topology.vertex_component]
        moved = vertices.copy()
        sel = which >= 0
        rel = vertices[sel] - origin[which[sel]]
        moved[sel] = np.einsum("vk,vkc->vc", rel, frames[which[sel]])   # R^T (x - x_a)
        return moved

    def all_frame_columns(self) -> np.ndarray:
        return frame_columns(self.topology.n_vertices, np.arange(self.topology.n_faces)).ravel()


ROUNDOFF_DEFECT = 10.0
"""Integrable forms skip the refinement where the integrability check's largest defect is
within this many times its tolerance (and the linear energy within it: :func:`
linear_answer_is_exact`). Needles make the holonomy of long loops accumulate round-off: the
layout of a face next to an edge 1e-6 of its size comes from its lengths with a relative
error ~1e-10, and the translation holonomy of a boundary loop of stanford-bunny with 350
edges split at 1e-6 of their length, exact forms, measured 1.02e-8 of the mean edge
(tolerance 1e-8) while the linear answer's energy was 1.8e-14 (1.7e-19 per edge): refined
for nothing, 3.5 times the linear time (bench.slivers)."""


def linear_answer_is_exact(energy: dict[str, float], tolerance: float, n_edges: int) -> bool:
    """Whether a linear answer of integrable forms is exact: its Eq. (5) energy (normalized
    units, edge and frame parts) is at most ``tolerance**2`` per edge, i.e. the residuals are
    at the integrability check's own tolerance.

    On meshes with needles and slivers the per-element residuals of an exact answer can
    exceed :func:`solver.refine.reproduces`'s thresholds through round-off alone, while the
    refinement of such a mesh is ill-conditioned; the verdict of the integrability check and
    this energy decide instead.

    Example:
        >>> linear_answer_is_exact({"edge": 1e-18, "frame": 2e-15}, 1e-8, 2000)
        True
        >>> linear_answer_is_exact({"edge": 1e-9, "frame": 0.0}, 1e-8, 2000)
        False
    """
    return sum(energy.values()) <= tolerance ** 2 * max(n_edges, 1)


def reconstruct(faces: ArrayLike, edges: ArrayLike, lengths: ArrayLike, angles: ArrayLike, *,
                constraints: Constraints | None = None,
                options: ReconstructOptions | None = None, n_vertices: int | None = None,
                layout_angles: np.ndarray | None = None,
                initial_guess: ArrayLike | None = None, progress: Progress | None = None,
                vertex_map: ArrayLike | None = None,
                placement: Placement | dict[str, Any] | None = None,
                **overrides: Any) -> Reconstruction:
    """Reconstruct vertex positions from edge lengths and dihedral angles (Eq. 5).

    Without constraints each component is anchored (one vertex at the origin, one frame at
    the identity). Integrable forms without constraints are integrated along spanning trees
    (Sec. 2.3; ``report["solve_path"]`` = "tree-integration", no factorization) when
    ``options.exact_shortcut``; otherwise K is factorized. ``options.orthonormalize``
    projects the frames to rotations and solves again with them as soft targets (Sec. 4);
    ``options.refine`` fits the nearest surface when the linear answer does not reproduce
    the forms (:mod:`solver.refine`, started from :mod:`solver.layout_fit`).

    Args:
        faces: (m, 3) int, counter-clockwise.
        edges: (E, 2) int, the faces' edges (i < j, sorted lexicographically).
        lengths: (E,) positive edge lengths (first fundamental form).
        angles: (E,) signed dihedral angles in (-pi, pi] (second fundamental form).
        constraints: optional :class:`Constraints` (positions and frames).
        options: :class:`solver.options.ReconstructOptions` (each field documents itself).
        n_vertices: vertex count (default ``faces.max() + 1``).
        layout_angles: optional (m,) rotation of each face's 2D frame; the vertices do not
            depend on it (Sec. 3), only the returned frames do.
        initial_guess: optional (n, 3) positions; the refinement starts from it instead
            of the layout fit when its energy is lower, e.g. the vertex blend of
            :func:`solver.interpolate` (and from the linear answer where that is lower
            still; ``report["refinement"]["start"]`` says which).
        progress: optional ``progress(stage, fraction)`` for the stages validate,
            assemble, factorize, solve (and refine); see :meth:`solver.refine.Refiner.run`
            for the per-iteration ``progress.iteration``.
        vertex_map: the forms' (n_cut,) file vertex of each vertex of ``faces`` (forms of a
            non-manifold mesh, :func:`solver.fundamental_forms`): the answer is given per
            file vertex, the mean of its copies, their spread in ``report["input"]["cut"]``
            (``n_vertices`` is then the file's vertex count).
        placement: the forms' component placement (:class:`solver.placement.Placement` or
            its dict): each component without constraints is moved rigidly so that its
            anchor face has that pose (a multi-part round trip is exact as a whole);
            without it each component is anchored at the origin and the anchored
            components are then laid out side by side along +x, without overlap
            (``report["input"]["placement"]`` says so).
        **overrides: fields of ``options`` given as keywords (``refine=False``).

    Returns:
        :class:`Reconstruction` with vertices (n, 3), frames (m, 3, 3) and a report
        (energies, ``timings`` per stage in seconds, backend, anchors, integrability,
        ``input``: wrapped angles, placement and cut).

    Example:
        >>> import numpy as np
        >>> from solver import fundamental_forms, reconstruct
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
        >>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> forms = fundamental_forms(V, F)
        >>> result = reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles)
        >>> result.report["solve_path"]
        'tree-integration'
        >>> rebuilt = fundamental_forms(result.vertices, F)
        >>> bool(np.allclose(rebuilt.lengths, forms.lengths))
        True
    """
    opts = ReconstructOptions.given(options, overrides)
    stages = Stages(progress)
    stages("validate")
    backend = resolve_backend(opts.backend or "auto")  # refused even when nothing factorizes
    cut = None
    if vertex_map is not None:
        cut = ManifoldCut.from_vertex_map(vertex_map, faces, n_vertices)
        n_vertices = cut.n_vertices
    topology, L, A = validate_forms(faces, edges, lengths, angles, n_vertices)
    place = Placement.coerce(placement, topology.n_faces)
    user = (constraints or Constraints()).validated(topology.n_vertices, topology.n_faces)
    stages.lap("validate")
    stages("assemble")
    problem = ImmersionProblem(topology, L, A, frame_weight=opts.frame_weight,
                               weighting=opts.weighting, cotan_floor=opts.cotan_floor,
                               length_scale=opts.length_scale, layout_angles=layout_angles)
    integrability = None
    known_not_integrable = nearly_integrable = False
    if opts.check_integrability:
        checked = integrability_from_terms(
            problem.terms, opts.integrability_tol, mean_length=float(L.mean()) /
            problem.length_scale, length_unit=problem.length_scale)
        integrability = checked.summary()
        # Forms that fail the check cannot have a zero-energy immersion: the tree
        # integration below would be built only to be refused. (Skipping it is never
        # wrong: the factorization gives the minimizer in every case.)
        known_not_integrable = not checked.integrable
        nearly_integrable = checked.max_defect <= ROUNDOFF_DEFECT * opts.integrability_tol
    linear = problem.linear_constraints(user)
    touched = problem.constrained_components(user)
    anchor, anchored = problem.anchors(~touched)
    linear = linear.extended(anchor)
    stages.lap("assemble")

    regularized: list[int] = []
    ref_v = np.zeros((topology.n_vertices, 3))
    pos_only, frame_only = problem.underdetermined_components(user)
    if len(pos_only) or len(frame_only):
        # The gauge left free by the constraints is pinned to an anchored reconstruction.
        stages("factorize")
        ref_anchor, _ = problem.anchors(np.ones_like(touched))
        ref_u = problem.system(ref_anchor, backend).solve(ref_anchor.hard_values,
                                                          np.zeros((0, 3)))
        ref_v, ref_f = problem.unknowns_to_geometry(ref_u)
        gauge, regularized = problem.gauge_constraints(user, ref_v, ref_f)
        linear = linear.extended(gauge)
        stages.lap("factorize")

    u = None
    if opts.exact_shortcut and not touched.any() and not known_not_integrable:
        # Integrable forms: the immersion integrated along spanning trees already has zero
        # energy, so it is the minimizer of Eq. 5 with these anchors (checked row by row).
        stages("solve")
        u = problem.integrated_solution([a["face"] for a in anchored],
                                        [a["vertex"] for a in anchored])
        stages.lap("solve")
        if u is not None:  # the factorization stage is skipped: report it as 0 s
            stages.timings["factorize"] = 0.0
            stages("factorize", 1.0)
    solve_path = "tree-integration" if u is not None else "factorization"
    factorized = {"backend": "none", "analysis": "none"}
    if u is None:
        stages("factorize")
        system = problem.system(linear, backend)
        stages.lap("factorize")
        stages("solve")
        u = system.solve(linear.hard_values, linear.soft_values)
        factorized = {"backend": system.backend, "analysis": system.analysis}
        # Dropped now, its analysis (the pattern of K) serves the orthonormalization's
        # factorization below: only the numerical phase is redone (solver.linalg's cache).
        del system
        stages.lap("solve")

    first_energy = problem.energies(u)
    energy = dict(first_energy)  # of the unknowns returned; redone if they change
    vertices, frames = problem.unknowns_to_geometry(u, user)
    vertices = problem.recenter(vertices, user, ref_v)
    orthonormality = _orthonormality_error(frames)
    refinement: dict[str, Any] = not_refined("exact: tree integration")
    refine = opts.refine
    if solve_path == "factorization":
        exact = refine is not False and reproduces(vertices, topology, L, A)
        refinement = not_refined("disabled (refine=false)" if refine is False
                                 else "exact: the linear answer reproduces the forms")
        if refine is not False and not exact and nearly_integrable and linear_answer_is_exact(
                first_energy, opts.integrability_tol, topology.n_edges):
            # Integrable forms never pay for a refinement: the verdict and the linear
            # energy decide it, not the per-element residuals of slivers (issue 40).
            exact = True
            refinement = not_refined("exact: integrable forms and a linear energy within "
                                     "the integrability tolerance")
    if opts.orthonormalize and solve_path == "factorization":  # integrated: rotations
        stages("factorize", 0.5)
        rotations = nearest_rotation(frames)
        cols = problem.all_frame_columns()
        system2 = problem.system(linear, backend, cols, opts.orthonormal_weight)
        stages.lap("factorize")
        stages("solve", 0.5)
        targets = np.swapaxes(rotations, 1, 2).reshape(-1, 3)
        soft_values = np.concatenate([linear.soft_values, targets])
        u = system2.solve(linear.hard_values, soft_values)
        vertices, frames = problem.unknowns_to_geometry(u, user)
        vertices = problem.recenter(vertices, user, ref_v)
        energy = problem.energies(u)
        stages.lap("solve")
    stages("solve", 1.0)
    if solve_path == "factorization" and refine is not False and not exact:
        stages("refine")
        vertices, refinement = _refined(problem, user, vertices, frames, anchored,
                                        initial_guess, opts, backend, stages, progress)
        frames = problem.frames_of(vertices)
        stages.lap("refine")
        stages("refine", 1.0)

    input_report: dict[str, Any] = {"wrapped_angles": wrapped_angle_count(angles),
                                     "zero_area_faces": len(flat_faces(topology, L)),
                                     "placement": "none"}
    laid_out = np.array([a["component"] for a in anchored], dtype=np.int64)
    if place is None and len(laid_out) > 1:
        # No placement: the anchored parts would all sit at the origin (issue 40).
        vertices = side_by_side(vertices, topology.vertex_component, laid_out)
        input_report["placement"] = (f"none: {len(laid_out)} components laid out side by "
                                     "side along +x")
    if place is not None:
        moving = ~touched[topology.face_component[place.faces]]
        vertices, frames = apply_placement(vertices, topology.faces, place.subset(moving),
                                           frames=frames)
        input_report["placement"] = f"{int(moving.sum())} of {len(moving)} components placed"
    if cut is not None:
        vertices, spread = cut.to_file(vertices)
        input_report["cut"] = cut.report(spread)
    report = ReconstructReport(
        energy=energy, first_solve_energy=first_energy,
        frame_orthonormality_error=orthonormality, orthonormalized=bool(opts.orthonormalize),
        refinement=refinement, timings=stages.timings, **factorized, solve_path=solve_path,
        n_unknowns=problem.n_unknowns, frame_weight=problem.frame_weight,
        weighting=problem.weighting, length_scale=problem.length_scale,
        regularized_components=regularized, anchored_components=anchored,
        isolated_vertices=topology.isolated_vertices.tolist(), integrability=integrability,
        warnings=as_report(refinement_warnings(refinement)), input=input_report)
    return Reconstruction(vertices=vertices, frames=frames, report=report)


def _refined(problem: ImmersionProblem, user: Constraints, vertices: np.ndarray,
             frames: np.ndarray, anchored: list[dict[str, int]],
             initial_guess: ArrayLike | None, opts: ReconstructOptions, backend: str,
             stages: Stages, progress: Progress | None) -> tuple[np.ndarray, dict[str, Any]]:
    """The refinement of :func:`reconstruct`: vertices (n, 3) nearest to the forms, started
    from the better of the layout fit of the linear answer and ``initial_guess``, moved back
    to the anchors; and its report."""
    topology = problem.topology
    start = problem.refinement_start(problem.layout_fit(user, backend), frames, user,
                                     vertices)
    targets = FormTargets(topology, problem.lengths, problem.angles,
                          angle_weight=opts.angle_weight)
    refiner = Refiner(targets, problem.refinement_handles(user), backend=backend)
    label = "layout fit"
    if initial_guess is not None:
        guess = as_points(initial_guess, "initial_guess")
        if guess.shape != start.shape:
            raise ConstraintError(f"initial_guess must have shape {start.shape}, got "
                                  f"{guess.shape}", field="initial_guess")
        if refiner.energy(guess) < refiner.energy(start):
            start, label = guess, "initial guess"
    if refiner.energy(vertices) < refiner.energy(start):
        # Needles of 1e-6 of their faces' size (issue 40): the layout fit of their tiny
        # edges' relative errors is ill-conditioned (13% form errors on stanford-bunny,
        # exact forms) where the linear answer is nearly exact.
        start, label = vertices, "linear answer"
    refiner.expect_refresh(stages.timings.get("factorize", 0.0))
    fit = refiner.run(start, time_limit=stages.budget(opts.max_seconds), progress=progress)
    refinement = dict(fit.report, start=label)
    vertices = fit.vertices
    # The errors on the well-shaped elements, reported for every refinement (slivers and
    # needles: issue 40); one that stopped short never leaves them worse than its start.
    before = well_shaped_errors(start, topology, problem.lengths, problem.angles,
                                refiner.form_energy)
    after = well_shaped_errors(vertices, topology, problem.lengths, problem.angles,
                               refiner.form_energy)
    refinement["well_shaped_error"] = {"start": before, "refined": after}
    if not refinement.get("converged") and after > before:
        vertices, refinement["returned"] = start, "start: the refined shape's errors on " \
            "well-shaped elements were larger"
    return problem.place_anchored(vertices, anchored), refinement


def _orthonormality_error(frames: np.ndarray) -> float:
    """max_t ||f_t^T f_t - I||_max: how far the solved frames are from rotations."""
    if not len(frames):
        return 0.0
    gram = np.swapaxes(frames, 1, 2) @ frames
    return float(np.abs(gram - np.eye(3)).max())
