"""Mesh deformation with position and orientation handles (Sec. 4-5).

The rest mesh's forms define the energy of Eq. (5); handles become constraints. The system
for a handle set is factorized once in :class:`Deformer`; each :meth:`Deformer.solve` only
back-substitutes (and, with ``orthonormalize``, runs the second solve of Sec. 4 against its
own cached factorization). With a region of interest the system is built on the faces that
touch the ROI only, so the cost follows the ROI size. ``linear_solver`` means what it means
for :func:`solver.reconstruct` (:func:`solver.reconstruct.linear_methods`): ``iterative``
(or ``auto`` where the factor would not fit) sets up a multigrid preconditioner once instead
of the factorization, each drag is then a CG solve started from the previous drag's answer,
and the refinement's Gauss-Newton steps are inexact CG steps too.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from .core.budget import Budget
from .core.errors import ConstraintError
from .core.serialization import JsonDataclass
from .core.validation import as_indices, as_points, require_unique
from .core.warnings import as_report, refinement_warnings
from .immersion import ImmersionProblem
from .linalg.iterative import RULES as LINEAR_SOLVER_RULES
from .linear.constraints import Constraints
from .linear.layout_fit import LayoutFit
from .linear.system import ConstrainedSystem, near_null_space
from .mesh.forms import forms_of, zero_area_faces
from .mesh.frames import layout_frames
from .mesh.manifold import ManifoldCut, manifold_topology
from .mesh.metrics import compact, distortion
from .mesh.rotations import is_rotation, nearest_rotation
from .mesh.topology import MeshTopology, build_topology
from .mesh.weld import check_welded_targets, one_handle_per_vertex, welded_mask
from .options import DeformOptions
from .reconstruct import linear_methods
from .refine.energy_weights import HARD_FRAME_WEIGHT
from .refine.form_energy import FormTargets, Handles
from .refine.outcomes import not_refined
from .refine.refiner import Refiner
from .reports import DeformReport, Progress, Stages


@dataclass
class Deformation(JsonDataclass):
    """Result of :func:`deform`: vertices (n, 3) float64 and a
    :class:`solver.reports.DeformReport` (timings, distortion)."""

    vertices: np.ndarray
    report: DeformReport

    _array_fields: ClassVar[dict[str, Any]] = {"vertices": np.float64}
    _nested_fields: ClassVar[dict[str, Any]] = {"report": DeformReport}


@dataclass(frozen=True)
class _RestState:
    """What a :class:`Deformer` derives from the rest mesh alone (shared, never mutated):
    the whole mesh's validated topology, the ROI's rest forms, its assembled
    :class:`ImmersionProblem` (with K) and rest frames."""

    topology: MeshTopology
    forms: Any
    problem: ImmersionProblem
    frames: np.ndarray
    cut: ManifoldCut


class _RestCache:
    """Per-process LRU of the last :data:`REST_CACHE_SIZE` rest states, keyed by a digest
    of the rest vertices, faces, ROI and energy options: a new handle set on a mesh (a
    session's next handle set) skips the forms and the assembly."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._entries: OrderedDict[bytes, _RestState] = OrderedDict()
        self.counts = {"computed": 0, "cached": 0}

    def get(self, key: bytes) -> _RestState | None:
        with self._lock:
            state = self._entries.get(key)
            self.counts["computed" if state is None else "cached"] += 1
            if state is not None:
                self._entries.move_to_end(key)
            return state

    def put(self, key: bytes, state: _RestState) -> None:
        with self._lock:
            self._entries[key] = state
            self._entries.move_to_end(key)
            while len(self._entries) > max(REST_CACHE_SIZE, 0):
                self._entries.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.counts = dict.fromkeys(self.counts, 0)


REST_CACHE_SIZE = 2
"""Rest states (meshes with their ROI) a process keeps for new :class:`Deformer` handle
sets; about 2 KB per face each (K and A). 0 disables the cache."""
_REST_CACHE = _RestCache()


def clear_rest_cache() -> None:
    """Forget every kept rest state and reset :func:`rest_cache_info`'s counters."""
    _REST_CACHE.clear()


def rest_cache_info() -> dict[str, int]:
    """``entries`` kept, and how many Deformers ``computed`` or reused (``cached``) theirs."""
    with _REST_CACHE._lock:
        return {"entries": len(_REST_CACHE._entries), **_REST_CACHE.counts}


def _rest_key(rest: np.ndarray, faces: np.ndarray, in_roi: np.ndarray,
              options: DeformOptions) -> bytes:
    """128-bit digest of everything a :class:`_RestState` depends on."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(repr((rest.shape, faces.shape, float(options.frame_weight),
                        options.weighting)).encode())
    for array in (rest, faces, in_roi):
        digest.update(memoryview(np.ascontiguousarray(array)).cast("B"))
    return digest.digest()


def _face_array(faces: ArrayLike) -> np.ndarray | None:
    """``faces`` as a C-contiguous (m, 3) int64 array when it plainly is one, else None
    (then only :func:`build_topology` looks at it, with its own errors)."""
    try:
        array = np.asarray(faces)
    except (TypeError, ValueError):
        return None
    if array.ndim != 2 or array.shape[1:] != (3,) or array.dtype.kind not in "iu":
        return None
    return np.ascontiguousarray(array, dtype=np.int64)


def _roi_mask(roi: ArrayLike | None, n: int) -> np.ndarray:
    """(n,) bool: the vertices that may move (all of them without a ``roi``)."""
    if roi is None:
        return np.ones(n, dtype=bool)
    in_roi = np.zeros(n, dtype=bool)
    in_roi[as_indices(roi, "roi", upper=n)] = True
    return in_roi


class Deformer:
    """Prefactorized deformation of one mesh under one set of handles.

    Args:
        vertices: (n, 3) rest positions.
        faces: (m, 3) int, counter-clockwise.
        handles: (h,) vertex indices whose positions are prescribed at each solve.
        rotation_handles: optional sequence of g face-index arrays; the frames of the faces
            in group i are rotated by ``handle_rotations[i]`` at each solve.
        roi: optional vertex indices that may move; every other vertex stays at rest.
            Default: all vertices.
        options: :class:`solver.options.DeformOptions` (each field documents itself);
            ``refine`` is the default of :meth:`solve`'s and None reads as off here: a
            refined drag costs factorizations of its own (bench/README.md), so an
            interactive client answers the linear shape first and :meth:`refine_last`
            after it; :func:`deform` refines by default. ``linear_solver`` (``"auto"``,
            ``"direct"``, ``"iterative"``) and ``memory_budget``: as for
            :func:`solver.reconstruct` (module docstring); :attr:`last_linear_solver` says
            which ran.
        progress: optional ``progress(stage, fraction)`` (validate, assemble, factorize).
        **overrides: fields of ``options`` given as keywords (``orthonormalize=True``).

    Example:
        >>> import numpy as np
        >>> from solver import Deformer
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> deformer = Deformer(V, F, handles=[0, 1, 2, 3])  # factorized once
        >>> lifted = deformer.solve(V[:4] + [0.0, 0.0, 1.0])  # a back-substitution
        >>> np.round(lifted - V, 6)[:, 2].tolist()  # a translation keeps the forms
        [1.0, 1.0, 1.0, 1.0, 1.0]
    """

    def __init__(self, vertices: ArrayLike, faces: ArrayLike, handles: ArrayLike, *,
                 rotation_handles: Sequence[ArrayLike] | None = None,
                 roi: ArrayLike | None = None, options: DeformOptions | None = None,
                 progress: Progress | None = None, **overrides: Any) -> None:
        self.options = opts = DeformOptions.given(options, overrides)
        stages = Stages(progress)
        stages("validate")
        self.file_rest = self.rest = as_points(vertices, "vertices")
        n = len(self.rest)
        # The rest-state cache is keyed by the faces as given (when they are an (m, 3)
        # integer array): a hit also skips validating the same connectivity again.
        given = _face_array(faces)
        in_roi = _roi_mask(roi, n)
        key = None if given is None else _rest_key(self.rest, given, in_roi, opts)
        rest = None if key is None else _REST_CACHE.get(key)
        # A non-manifold mesh is solved on its manifold cut (solver.mesh.manifold): handles and
        # the ROI name file vertices (every copy follows), answers are per file vertex.
        cut_topology = None
        if rest is not None:
            self.cut = rest.cut
        else:
            self.cut, cut_topology = manifold_topology(faces, self.rest)
        self.file_faces = np.asarray(given if given is not None else self.cut.faces,
                                     dtype=np.int64)
        self.file_handles = as_indices(handles, "handles", upper=n)
        require_unique(self.file_handles, "handles", "vertex")
        self.handles, self._handle_source, self._welded_handles = one_handle_per_vertex(
            *self.cut.copies_of(self.file_handles))
        if not self.cut.is_identity:
            self.rest = self.cut.to_cut(self.rest)
            in_roi = welded_mask(self.cut.weld_map, in_roi)[self.cut.vertex_map]
            n = len(self.rest)
        full = rest.topology if rest is not None else cut_topology
        self.faces = full.faces
        self.last_spread = np.zeros(len(self.file_rest))
        """(n_file,) largest distance of a file vertex's copies from their mean in the last
        answer (0 for a manifold mesh)."""
        n_file_faces = self.cut.n_file_faces or len(self.faces)
        groups = [self.cut.to_solve_faces(as_indices(g, f"rotations[{i}].faces",
                                                     upper=n_file_faces),
                                          f"rotations[{i}].faces")
                  for i, g in enumerate(rotation_handles or [])]
        for i, g in enumerate(groups):
            if len(g) == 0:
                raise ConstraintError("an orientation handle needs at least one face",
                                      field=f"rotations[{i}].faces")
        all_rot = np.concatenate(groups) if groups else np.zeros(0, np.int64)
        require_unique(all_rot, "rotations.faces", "face")
        if len(self.handles) == 0 and len(all_rot) == 0:
            raise ConstraintError("give at least one position or orientation handle",
                                  field="handles")

        # Region of interest: faces touching it form the system; other vertices are fixed.
        outside = np.flatnonzero(~in_roi[self.handles])
        if len(outside):
            raise ConstraintError(f"handle vertex {int(self.handles[outside[0]])} is outside "
                                  "the region of interest", field="handles",
                                  index=int(outside[0]))
        self._refuse_handles_in_no_face(full)
        sub_faces_mask = in_roi[self.faces].any(axis=1)
        rot_outside = np.flatnonzero(~sub_faces_mask[all_rot])
        if len(rot_outside):
            raise ConstraintError(f"rotation face {int(all_rot[rot_outside[0]])} does not touch "
                                  "the region of interest", field="rotations.faces",
                                  index=int(rot_outside[0]))
        self.in_roi = in_roi
        self.sub_faces = np.flatnonzero(sub_faces_mask)
        self.sub_vertices = np.unique(self.faces[self.sub_faces])
        local_index = np.full(n, -1, dtype=np.int64)
        local_index[self.sub_vertices] = np.arange(len(self.sub_vertices))
        local_faces = local_index[self.faces[self.sub_faces]]
        face_local = np.full(len(self.faces), -1, dtype=np.int64)
        face_local[self.sub_faces] = np.arange(len(self.sub_faces))

        sub_rest = self.rest[self.sub_vertices]
        stages.lap("validate")
        stages("assemble")
        self.rest_state = "computed" if rest is None else "cached"
        if rest is None:
            # The mesh's topology is built once: the whole mesh's serves when the system
            # covers it (every vertex used, every face in the ROI), else the sub-mesh's.
            whole = len(self.sub_vertices) == n and len(self.sub_faces) == len(self.faces)
            topology = full if whole else build_topology(local_faces,
                                                         n_vertices=len(sub_rest))
            forms = forms_of(sub_rest, topology)
            problem = ImmersionProblem(topology, forms.lengths, forms.angles,
                                       frame_weight=opts.frame_weight,
                                       weighting=opts.weighting)
            frames = layout_frames(sub_rest / problem.length_scale, forms.faces,
                                   problem.terms.layouts)
            rest = _RestState(full, forms, problem, frames, self.cut)
        forms, self.problem, self.rest_frames = rest.forms, rest.problem, rest.frames
        fixed_local = np.flatnonzero(~in_roi[self.sub_vertices])
        self._handle_local = local_index[self.handles]
        self._fixed_local = fixed_local
        self._group_faces = [face_local[g] for g in groups]
        self._handle_weight = float(opts.handle_weight)
        self._rotation_weight = float(opts.rotation_weight)
        self.refine = opts.refine is True
        self.backend_name = opts.backend or "auto"
        self.rest_forms = forms
        self.last_report: dict[str, Any] = not_refined("no solve yet")
        self._refiner: Refiner | None = None
        self._layout_fit: LayoutFit | None = None
        self._previous: tuple[np.ndarray, np.ndarray] | None = None  # (linear, refined)
        # The last solve's targets and answers, for refine_last (see there).
        self._last: dict[str, Any] | None = None

        template = self._constraints(np.zeros((len(self.handles), 3)),
                                     np.tile(np.eye(3), (len(groups), 1, 1)))
        linear = self.problem.linear_constraints(template)
        touched = self.problem.constrained_components(template)
        # Components without any handle stay at rest; underdetermined ones lean on the rest.
        anchor, _ = self.problem.anchors(~touched, sub_rest, self.rest_frames)
        self._anchor = anchor.extended(self.problem.gauge_constraints(
            template, sub_rest, self.rest_frames)[0])
        linear = linear.extended(self._anchor)
        self.linear_method, self.refine_method = linear_methods(
            self.problem.topology.n_faces, opts.linear_solver, opts.memory_budget)
        self._guess: np.ndarray | None = None
        self._near_null: np.ndarray | None = None
        if self.linear_method == "iterative":
            # The rest mesh is an immersion of its own forms: CG's first start and, with the
            # translation, the near-null space the multigrid keeps exact.
            self._guess = np.concatenate([sub_rest / self.problem.length_scale,
                                          np.swapaxes(self.rest_frames, 1, 2).reshape(-1, 3)])
            self._near_null = near_null_space(len(sub_rest), self._guess).astype(
                LINEAR_SOLVER_RULES.preconditioner_dtype)
        self.last_linear_solver: dict[str, Any] | None = None
        """How the last :meth:`solve` solved Eq. 5
        (:meth:`~solver.linear.constrained.ConstrainedSystem.linear_solver_report`:
        ``{"method": "direct", "backend"}`` or the CG statistics; ``first_solve``: the first
        solve's, under ``orthonormalize``); None before one."""
        stages.lap("assemble")
        stages("factorize")
        # PARDISO's own ordering: its two-level factor solves each drag 1.3-1.5x faster
        # than a factor of the hinted ordering (bench/drag_regression.py).
        self.system: ConstrainedSystem = self.problem.system(
            linear, self.backend_name, ordering_hint=False, method=self.linear_method,
            near_null=self._near_null)
        if key is not None:
            _REST_CACHE.put(key, rest)  # after the first factorization: K is assembled
        self._linear = linear
        self.system_orthonormal: ConstrainedSystem | None = None
        if opts.orthonormalize:
            self._orthonormal_system()
        if self.refine:  # the refinement's start, pattern and analysis: not in a drag
            self._start_fit()
            self._refinement().prepare()
        stages.lap("factorize")
        self.setup_timings = stages.timings
        """Seconds of the stages validate, assemble and factorize of the set-up."""
        self.setup_seconds = sum(self.setup_timings.values())
        stages("factorize", 1.0)

    def _orthonormal_system(self) -> ConstrainedSystem:
        """The system of the second solve of Sec. 4 (factorized on first use)."""
        if self.system_orthonormal is None:
            self.system_orthonormal = self.problem.system(
                self._linear, self.backend_name, self.problem.all_frame_columns(),
                self.options.orthonormal_weight, ordering_hint=False,
                method=self.linear_method, near_null=self._near_null)
        return self.system_orthonormal

    def _start_fit(self) -> LayoutFit:
        """The refinement's start: positions fitted to rotated layouts (built on first use;
        the same fixed and soft vertices as the refinement)."""
        if self._layout_fit is None:
            template = self._constraints(np.zeros((len(self.handles), 3)),
                                         np.tile(np.eye(3), (self.n_groups, 1, 1)))
            self._layout_fit = self.problem.layout_fit(template, self.backend_name)
        return self._layout_fit

    def _refinement(self) -> Refiner:
        """The nonlinear fit of the ROI to its rest forms (built on first use)."""
        if self._refiner is None:
            topology = self.problem.topology
            hard = np.isinf(self._handle_weight)
            local_faces = (np.concatenate(self._group_faces) if self._group_faces
                           else np.zeros(0, np.int64))
            fixed = np.concatenate([self._fixed_local, self._handle_local if hard
                                    else np.zeros(0, np.int64)])
            soft = np.zeros(0, np.int64) if hard else self._handle_local
            weight = (HARD_FRAME_WEIGHT if np.isinf(self._rotation_weight)
                      else self._rotation_weight)
            handles = Handles(
                fixed=fixed, soft_vertices=soft,
                soft_positions=self.rest[self.sub_vertices[soft]],
                soft_weights=np.full(len(soft), self._handle_weight),
                frame_faces=local_faces, frame_edges=np.zeros((len(local_faces), 2, 3)),
                frame_weights=np.full(len(local_faces), weight))
            targets = FormTargets(topology, self.rest_forms.lengths, self.rest_forms.angles,
                                  angle_weight=self.options.angle_weight)
            self._refiner = Refiner(targets, handles, backend=self.backend_name,
                                    linear_solver=self.refine_method)
        return self._refiner

    def _rest_face_edges(self, rotations: np.ndarray) -> np.ndarray:
        """(q, 2, 3) rest edge vectors x1 - x0, x2 - x0 of the orientation-handle faces,
        rotated by their group's rotation."""
        if not self._group_faces:
            return np.zeros((0, 2, 3))
        faces = self.problem.topology.faces[np.concatenate(self._group_faces)]
        group_of = np.repeat(np.arange(self.n_groups), [len(g) for g in self._group_faces])
        rest = self.rest[self.sub_vertices]
        edges = np.stack([rest[faces[:, 1]] - rest[faces[:, 0]],
                          rest[faces[:, 2]] - rest[faces[:, 0]]], axis=1)   # (q, 2, 3)
        return np.einsum("qij,qej->qei", rotations[group_of], edges)

    @property
    def n_groups(self) -> int:
        return len(self._group_faces)

    @property
    def backend(self) -> str:
        return self.system.backend

    def _constraints(self, handle_positions: np.ndarray,
                     handle_rotations: np.ndarray) -> Constraints:
        local_faces = (np.concatenate(self._group_faces) if self._group_faces
                       else np.zeros(0, np.int64))
        group_of = np.repeat(np.arange(self.n_groups),
                             [len(g) for g in self._group_faces]).astype(np.int64)
        frames = handle_rotations[group_of] @ self.rest_frames[local_faces]
        fixed = self._fixed_local
        return Constraints(
            position_vertices=np.concatenate([self._handle_local, fixed]),
            positions=np.concatenate([handle_positions, self.rest[self.sub_vertices[fixed]]]),
            position_weights=np.concatenate([np.full(len(self._handle_local),
                                                     self._handle_weight),
                                             np.full(len(fixed), np.inf)]),
            frame_faces=local_faces, frames=frames,
            frame_weights=np.full(len(local_faces), self._rotation_weight))

    def _refuse_handles_in_no_face(self, topology: MeshTopology) -> None:
        """Raise when a handle names a vertex no face uses (an unreferenced vertex of the
        file, or one whose faces were dropped as degenerate): it has no place in the
        system, so it could neither move the surface nor be placed by it."""
        lonely = np.flatnonzero(~topology.is_referenced[self.handles])
        if len(lonely):
            at = int(self._handle_source[lonely[0]])
            vertex = int(self.file_handles[at])
            raise ConstraintError(
                f"handle vertex {vertex} is in no face (no face of the file uses it, or its "
                "faces were dropped as degenerate): it cannot move the surface; leave it out "
                "of the handles", field="handles", index=at, details={"value": vertex})

    def solve(self, handle_positions: ArrayLike | None = None,
              handle_rotations: ArrayLike | None = None, refine: bool | None = None,
              max_seconds: float | None = None, progress: Progress | None = None,
              ) -> np.ndarray:
        """Deformed vertices (n, 3) for new handle targets; only back-substitutes.

        Args:
            handle_positions: (h, 3) target positions of ``handles`` (default: rest).
            handle_rotations: (g, 3, 3) rotations of the orientation handles (default: I).
            refine: fit the rest forms nonlinearly from the linear answer (default: the
                ``refine`` given at construction); skipped when the linear answer already
                has the rest forms (e.g. a rigid motion of every handle).
                :attr:`last_report` says whether and how it refined.
            max_seconds: optional budget of this call, the linear solve included: the
                refinement gets what the linear answer leaves (see :meth:`refine_last`).
            progress: optional callback for the refinement's steps (see there).
        """
        budget = Budget.of(max_seconds)
        refine = self.refine if refine is None else bool(refine)
        P = (self.file_rest[self.file_handles] if handle_positions is None
             else as_points(handle_positions, "handle_positions"))
        if len(P) != len(self.file_handles):
            raise ConstraintError(f"expected {len(self.file_handles)} handle positions, got "
                                  f"{len(P)}", field="handle_positions")
        check_welded_targets(P, self.file_handles, self._welded_handles, self.file_rest)
        P = P[self._handle_source]  # every copy of a handle vertex follows it
        R = (np.tile(np.eye(3), (self.n_groups, 1, 1)) if handle_rotations is None
             else np.asarray(handle_rotations, dtype=np.float64).reshape(-1, 3, 3))
        if len(R) != self.n_groups:
            raise ConstraintError(f"expected {self.n_groups} rotations, got {len(R)}",
                                  field="handle_rotations")
        bad = np.flatnonzero(~is_rotation(R))
        if len(bad):
            raise ConstraintError("not a rotation matrix (orthonormal with det +1)",
                                  field="handle_rotations", index=int(bad[0]))
        constraints = self._constraints(P, R)
        linear = self.problem.linear_constraints(constraints).extended(self._anchor)
        u = self.system.solve(linear.hard_values, linear.soft_values, self._guess)
        self.last_linear_solver = self.system.linear_solver_report()
        _, frames = self.problem.unknowns_to_geometry(u)
        if self.options.orthonormalize:
            targets = np.swapaxes(nearest_rotation(frames), 1, 2).reshape(-1, 3)
            system = self._orthonormal_system()
            u = system.solve(linear.hard_values, np.concatenate([linear.soft_values, targets]),
                             u)
            if system.iterative is not None:
                self.last_linear_solver = {**system.linear_solver_report(),
                                           "first_solve": self.last_linear_solver}
            _, frames = self.problem.unknowns_to_geometry(u)
        if self._guess is not None:  # CG: the next drag starts from this one's answer
            self._guess = u
        local, _ = self.problem.unknowns_to_geometry(u, constraints)
        local = self.problem.recenter(local, constraints, self.rest[self.sub_vertices])
        self._last = {"P": P, "R": R, "constraints": constraints, "linear": local,
                      "frames": frames, "best": None, "report": None}
        self.last_report = not_refined("disabled (refine=false)")
        if refine:
            return self.refine_last(budget, progress)
        return self._embed(local)

    def expect_refresh(self, seconds: float) -> None:
        """An estimate of one factorization of the refinement before it has timed one
        (:meth:`solver.refine.Refiner.expect_refresh`): a budget then stops before the first
        one too. :func:`deform` gives the set-up's; a session's drags do not, so that a
        frame budget shorter than a factorization still gets its first."""
        self._refinement().expect_refresh(seconds)

    def refine_last(self, max_seconds: Budget | float | None = None,
                    progress: Progress | None = None) -> np.ndarray:
        """The refined shape (n, 3) for the handle targets of the last :meth:`solve`.

        The first call after a solve starts from the better (lower energy) of the layout
        fit of that solve's rotations and the previous drag's refined shape moved by what
        the linear answer moved; a call after a refinement that stopped early (its budget
        ``max_seconds``, a :class:`~solver.core.budget.Budget` or seconds from now, which counts
        the choice of the start too, ran out:
        ``last_report["stop_reason"] == "time_limit"``) continues from where it stopped, so
        an interactive client can answer the linear shape at once and refine in slices
        while the user pauses. A converged refinement is
        returned as it is. :attr:`last_report` is the refinement's report. ``progress``:
        ``progress("refine", fraction)`` after each step, and ``progress.iteration(detail)``
        where it has that method (:meth:`solver.refine.Refiner.run`).
        """
        budget = Budget.of(max_seconds)
        if self._last is None:
            raise ConstraintError("nothing to refine: call solve first", field="handles")
        last = self._last
        if last["best"] is not None and last["report"].get("converged"):
            return self._embed(last["best"])
        refiner = self._refinement()
        local = last["linear"]
        if last["best"] is None and refiner.reproduces(local):
            self.last_report = not_refined("exact: the linear answer has the rest forms")
            last["best"], last["report"] = local, self.last_report
            return self._embed(local)
        if last["best"] is not None and refiner.can_resume:
            # The previous slice of this drag stopped at its budget: continue it exactly.
            fit = refiner.resume(budget, progress)
            label = last["report"].get("start")
        else:
            soft = None if np.isinf(self._handle_weight) else last["P"]
            refiner.set_handle_targets(soft, self._rest_face_edges(last["R"]))
            start, label = last["best"], "previous slice"
            if start is None:
                start, label = self.problem.refinement_start(
                    self._start_fit(), last["frames"], last["constraints"], local), "layout fit"
                energy = refiner.energy(start)
                if self._previous is not None:
                    # A session's next drag: the previous refined shape, moved by what the
                    # linear answer moved (exactly the new targets at hard handles). Of the
                    # two starts the nearer to the rest forms wins.
                    warm = self._previous[1] + (local - self._previous[0])
                    warm_energy = refiner.energy(warm)
                    if warm_energy < energy:
                        start, label, energy = warm, "previous drag", warm_energy
            else:
                energy = None
            fit = refiner.run(start, keep_factor=True,
                              time_limit=budget,
                              progress=progress, start_energy=energy)
        self.last_report = dict(fit.report, start=label)
        last["best"], last["report"] = fit.vertices, self.last_report
        self._previous = (local, fit.vertices)
        return self._embed(fit.vertices)

    def _embed(self, local: np.ndarray) -> np.ndarray:
        """Whole-mesh vertices (n, 3) per file vertex: the rest, with the ROI's vertices
        from ``local`` (copies of a file vertex averaged, :attr:`last_spread`)."""
        out = self.rest.copy()
        moving = self.in_roi[self.sub_vertices]
        out[self.sub_vertices[moving]] = local[moving]
        if self.cut.is_identity:
            return out
        out, self.last_spread = self.cut.to_file(out)
        return out


def deform(vertices: ArrayLike, faces: ArrayLike, handles: ArrayLike,
           handle_positions: ArrayLike, *, rotation_handles: Sequence[ArrayLike] | None = None,
           handle_rotations: ArrayLike | None = None, roi: ArrayLike | None = None,
           options: DeformOptions | None = None, progress: Progress | None = None,
           **overrides: Any) -> Deformation:
    """One-shot deformation: build a :class:`Deformer`, solve once, measure distortion.

    Args:
        vertices, faces, handles, rotation_handles, roi: as for :class:`Deformer`.
        handle_positions: (h, 3) targets of ``handles``.
        handle_rotations: optional (g, 3, 3) rotations of the orientation handles.
        options: :class:`solver.options.DeformOptions`; ``refine`` None (the default) and
            True fit the rest forms nonlinearly from the linear answer unless it already has
            them (:mod:`solver.refine`), False returns the linear answer; ``max_seconds``
            budgets the whole call (the refinement stops when it runs out);
            ``linear_solver`` (``"auto"`` default, ``"direct"``, ``"iterative"``): how Eq.
            5 and the refinement's steps are solved, as for :func:`solver.reconstruct`.
        progress: optional ``progress(stage, fraction)`` (validate ... refine).
        **overrides: fields of ``options`` given as keywords.

    Returns:
        :class:`Deformation` whose report holds ``timings`` per stage, the backend, how Eq.
        5 was solved (``linear_solver``: ``{"method": "direct", "backend"}`` or the CG
        statistics), whether and how it refined (``refinement``, its steps' solver in
        ``refinement.linear_solver``) and the distortion against the rest mesh
        (:func:`solver.mesh.metrics.distortion`, without per-edge arrays).

    Example:
        >>> import numpy as np
        >>> from solver import deform
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> moved = deform(V, F, [0, 1, 2, 3], V[:4] * 2.0, refine=False)
        >>> moved.vertices[:4].tolist() == (V[:4] * 2.0).tolist()  # hard handles
        True
        >>> sorted(moved.report["timings"])
        ['assemble', 'factorize', 'solve', 'validate']
    """
    opts = DeformOptions.given(options, overrides)
    deformer = Deformer(vertices, faces, handles, rotation_handles=rotation_handles, roi=roi,
                        options=opts.replace(refine=opts.refine is not False),
                        progress=progress)
    stages = Stages(progress)
    stages.started -= deformer.setup_seconds  # the budget counts the set-up
    stages("solve")
    result = deformer.solve(handle_positions, handle_rotations, refine=False)
    stages.lap("solve")
    if deformer.refine:
        stages("refine")
        deformer.expect_refresh(deformer.setup_timings.get("factorize", 0.0))
        result = deformer.refine_last(stages.budget(opts.max_seconds), progress)
        stages.lap("refine")
    # The last stage that ran is complete.
    stages("refine" if deformer.last_report.get("refined") else "solve", 1.0)
    report = DeformReport(
        timings={**deformer.setup_timings, **stages.timings}, backend=deformer.backend,
        analysis=deformer.system.analysis, n_unknowns=deformer.problem.n_unknowns,
        roi_faces=len(deformer.sub_faces), orthonormalized=bool(opts.orthonormalize),
        refinement=deformer.last_report,
        distortion=compact(distortion(deformer.rest, deformer.cut.to_cut(result),
                                      deformer.faces, coincident=False)),
        warnings=as_report(refinement_warnings(deformer.last_report)),
        linear_solver=deformer.last_linear_solver)
    if not deformer.cut.is_identity:
        vertex = report.distortion.get("vertex")
        if vertex is not None:
            report.distortion["vertex"] = deformer.cut.to_file(np.asarray(vertex))[0]
        report.input = deformer.cut.sections(deformer.last_spread)
    flat = zero_area_faces(deformer.rest, deformer.faces)
    if len(flat):  # collinear corners (issue 40): counted
        report.input = {**(report.input or {}), "zero_area_faces": len(flat)}
    return Deformation(vertices=result, report=report)
