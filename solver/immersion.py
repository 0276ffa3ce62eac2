"""The linear problem of Eq. (5) for one set of forms: :class:`ImmersionProblem`.

It holds the assembled energy (layouts, coefficients, rotations, weights; the residual
operator and its normal matrix) in units of a length scale, and what :func:`solver.reconstruct`,
:class:`solver.deform.Deformer`, :func:`solver.parameterize` and the adjoints need of it:
constraints turned into linear ones, unknowns turned back into vertices and frames, the tree
integration of integrable forms, the refinement's start and handles.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from .core.errors import ConstraintError, TriangleInequalityError
from .linear.constraints import Constraints
from .linear.layout_fit import LayoutFit
from .linear.system import (
    WEIGHTINGS,
    ConstrainedSystem,
    EnergyTerms,
    LinearConstraints,
    Weighting,
    energies,
    energy_terms,
    frame_columns,
    least_squares_rows,
    normal_matrix,
    residual_summary,
    unknown_groups,
)
from .linear.tree_integration import (
    IntegrationForests,
    integrated_unknowns,
    integration_forests,
)
from .mesh.frames import (
    face_edge_lengths,
    layout_frames,
    triangle_inequality_error,
    triangle_inequality_violations,
)
from .mesh.rotations import nearest_rotation
from .mesh.topology import MeshTopology
from .options import COTAN_FLOOR, FRAME_WEIGHT
from .refine.energy_weights import HARD_FRAME_WEIGHT
from .refine.form_energy import Handles

REGULARIZATION = 1e-6
EXACT_TOLERANCE = 1e-10  # residual rows (normalized lengths) accepted without a solve


class ImmersionProblem:
    """The energy of Eq. (5) for one set of forms, in units of ``length_scale``.

    Attributes:
        terms: layouts, coefficients, rotations, weights.
        A, row_weights, row_kind: the residual operator (see :mod:`solver.linear.system`).
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
        self._energy: tuple[np.ndarray, dict[str, float]] | None = None  # (u, energies), once

    @functools.cached_property
    def _rows(self) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
        """Eq. 5's rows (:func:`least_squares_rows`), built on first use (the tree
        integration's answer never needs them)."""
        return least_squares_rows(self.terms, self.frame_weight)

    @property
    def A(self) -> sp.csr_matrix:  # noqa: N802 - the matrix of the paper
        """(rows, N) CSR residual operator (:func:`least_squares_rows`)."""
        return self._rows[0]

    @property
    def row_weights(self) -> np.ndarray:
        """(rows,) float64 weights of the rows of :attr:`A`."""
        return self._rows[1]

    @property
    def row_kind(self) -> np.ndarray:
        """(rows,) int8 kind of the rows of :attr:`A` (0 edge, 1 frame)."""
        return self._rows[2]

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
        kept, self._energy = self._energy, None
        if kept is not None and kept[0] is u:
            return dict(kept[1])
        if "_rows" not in self.__dict__:  # released (or never built): from the terms
            return residual_summary(self.terms, self.frame_weight, u)[1]
        return energies(self.A, self.row_weights, self.row_kind, u)

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

    def tree_unknowns(self, root_faces: ArrayLike, root_vertices: ArrayLike) -> np.ndarray:
        """Unknowns (N, 3) integrated along spanning trees from the anchors (frame I at
        each root face, origin at each root vertex), whatever the forms' integrability
        (noisy forms accumulate their errors along the trees; possibly non-finite)."""
        return self._tree_integration(root_faces, root_vertices)[0]

    def _tree_integration(self, root_faces: ArrayLike, root_vertices: ArrayLike,
                          ) -> tuple[np.ndarray, IntegrationForests]:
        """:meth:`tree_unknowns` and the forests they were integrated along."""
        forests = integration_forests(self.terms, np.asarray(root_faces, dtype=np.int64),
                                      np.asarray(root_vertices, dtype=np.int64))
        return integrated_unknowns(self.terms, forests), forests

    def integrated_solution(self, root_faces: ArrayLike, root_vertices: ArrayLike,
                            tol: float = EXACT_TOLERANCE) -> np.ndarray | None:
        """Unknowns (N, 3) integrated along spanning trees from the anchors (frame I at
        each root face, origin at each root vertex), or None if some weighted residual row
        of Eq. 5 exceeds ``tol`` (the forms are not integrable to that accuracy)."""
        u, forests = self._tree_integration(root_faces, root_vertices)
        if not np.isfinite(u).all():
            return None
        # The frame rows of the dual forest's edges hold by construction (f_child = f_parent
        # R, one rounding): only the other interior edges' frame rows are evaluated.
        worst, energy = residual_summary(self.terms, self.frame_weight, u,
                                         np.flatnonzero(~forests.dual.in_tree))
        if worst > tol:
            return None
        self._energy = (u, energy)  # energies(u) reuses it
        return u

    def system(self, constraints: LinearConstraints, backend: str = "auto",
               extra_penalty_columns: np.ndarray | None = None,
               extra_penalty_weight: float = 0.0,
               ordering_hint: bool = True, method: str = "direct",
               near_null: np.ndarray | Callable[[], np.ndarray | None] | None = None,
               release: bool = False
               ) -> ConstrainedSystem:
        """Factorize K with ``constraints`` (and optional extra soft columns, e.g. every
        frame for the orthonormalization solve). ``ordering_hint``: pass the unknowns'
        groups to :func:`solver.linalg.factorize` (a cheaper analysis, slower solves); False
        for a system solved per drag. ``method="iterative"``: no factorization, a multigrid
        preconditioner on ``near_null`` (:class:`solver.linear.system.ConstrainedSystem`).
        ``release``: the problem lets go of K as it hands it over (assembled again if it is
        used later), so that K is freed as soon as the system has made its own constrained
        copy, before the factorization or the multigrid setup, and does not stay alive
        through the refinement (about 12 bytes per nonzero: 0.9 GB at 1.6M faces)."""
        soft_cols, soft_w = constraints.soft_columns, constraints.soft_weights
        if extra_penalty_columns is not None:
            soft_cols = np.concatenate([soft_cols, extra_penalty_columns])
            soft_w = np.concatenate([soft_w, np.full(len(extra_penalty_columns),
                                                     extra_penalty_weight)])
        topo = self.topology
        groups = unknown_groups(topo.n_vertices, topo.n_faces) if ordering_hint else None
        return ConstrainedSystem(self._handed_over_K if release else self.K,
                                 constraints.hard_columns, soft_cols, soft_w, backend, groups,
                                 method=method, near_null=near_null)

    def _handed_over_K(self) -> sp.csc_matrix:  # noqa: N802 - the matrix of the paper
        """K, forgotten by this problem (:attr:`K` assembles it again on a later use)."""
        K = self.K
        del self.__dict__["K"]
        # The last system: Eq. 5's rows (and the rotations in them) served K only; they are
        # not held through its factorization or multigrid setup (~360 bytes per face).
        # :meth:`energies` reads the terms from here on (equal to rounding).
        self.__dict__.pop("_rows", None)
        self.terms.__dict__.pop("rotations", None)
        return K

    def release_linear(self) -> None:
        """Forget what only Eq. 5's solves use: its rows (:attr:`A`, :attr:`row_weights`,
        :attr:`row_kind`), :attr:`K`, the kept energy and the terms' transition rotations and
        quaternions (each assembled again on a later use). :func:`solver.reconstruct` calls
        it before the refinement, which needs none of them (its own matrices are built from
        the forms): ~360 bytes per face, 36 MB at 100K faces, ~0.6 GB at 1.6M."""
        for name in ("_rows", "K"):
            self.__dict__.pop(name, None)
        self.release_transitions()
        self._energy = None

    def release_transitions(self) -> None:
        """Forget the terms' transition rotations and quaternions (the tree integration's
        and the holonomy check's; assembled again on a later use): 128 bytes per interior
        edge, 0.3 GB at 1.6M faces."""
        for name in ("rotations", "quaternions"):
            self.terms.__dict__.pop(name, None)

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
        """The refinement's start (:class:`solver.linear.layout_fit.LayoutFit`) for validated user
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
