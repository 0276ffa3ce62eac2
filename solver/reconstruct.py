"""Vertex positions from discrete fundamental forms: one sparse linear solve (Sec. 3-4).

:class:`~solver.immersion.ImmersionProblem` holds the assembled energy of Eq. (5) for a set
of forms; :func:`reconstruct` adds constraints (or anchors), factorizes once and solves for
the three coordinates; with ``orthonormalize=True`` it projects the frames to rotations and
solves again with them as soft constraints (Sec. 4). :class:`solver.deform.Deformer` reuses
the same pieces.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from .answer_map import AnswerMap
from .core.errors import ConstraintError
from .core.serialization import JsonDataclass
from .core.validation import as_points
from .core.warnings import as_report, refinement_warnings
from .immersion import ImmersionProblem
from .linalg import resolve_backend
from .linalg.iterative import RULES as LINEAR_SOLVER_RULES
from .linalg.iterative import available_memory
from .linear.constraints import Constraints
from .linear.integrability import integrability_from_terms
from .linear.system import near_null_space
from .mesh.forms import flat_faces, validate_forms, wrapped_angle_count
from .mesh.manifold import ManifoldCut
from .mesh.placement import Placement
from .mesh.rotations import nearest_rotation
from .options import ReconstructOptions
from .refine.form_energy import FormTargets, reproduces, well_shaped_errors
from .refine.iterative_steps import REFINEMENT_SOLVER_RULES
from .refine.outcomes import not_refined
from .refine.refiner import Refiner
from .reports import Progress, ReconstructReport, Stages


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


def linear_methods(n_faces: int, linear_solver: str | None,
                   memory_budget: float | None) -> tuple[str, str]:
    """How the solves of a mesh of ``n_faces`` faces run under the ``linear_solver`` option
    (:class:`solver.options.ReconstructOptions`; :class:`solver.Deformer` reads it the same
    way): ``(method, refine_method)``, each ``"direct"`` or ``"iterative"``, of Eq. 5's
    linear system and of the refinement's Gauss-Newton steps; ``auto`` chooses by the size
    and the memory available (``memory_budget``, :func:`solver.linalg.iterative.
    available_memory`).

    Example:
        >>> linear_methods(1000, "iterative", None), linear_methods(1000, "direct", None)
        (('iterative', 'iterative'), ('direct', 'direct'))
    """
    memory = available_memory(memory_budget)
    method = LINEAR_SOLVER_RULES.choose(n_faces, linear_solver, memory)
    # The refinement's factor takes more memory than Eq. 5's: it may go iterative alone.
    refine_method = "iterative" if method == "iterative" else REFINEMENT_SOLVER_RULES.choose(
        n_faces, linear_solver, memory)
    return method, refine_method


def reconstruct(faces: ArrayLike, edges: ArrayLike, lengths: ArrayLike, angles: ArrayLike, *,
                constraints: Constraints | None = None,
                options: ReconstructOptions | None = None, n_vertices: int | None = None,
                layout_angles: np.ndarray | None = None,
                initial_guess: ArrayLike | None = None, progress: Progress | None = None,
                vertex_map: ArrayLike | None = None,
                placement: Placement | dict[str, Any] | None = None,
                weld_map: ArrayLike | None = None,
                **overrides: Any) -> Reconstruction:
    """Reconstruct vertex positions from edge lengths and dihedral angles (Eq. 5).

    Without constraints each component is anchored (one vertex at the origin, one frame at
    the identity). Integrable forms without constraints are integrated along spanning trees
    (Sec. 2.3; ``report["solve_path"]`` = "tree-integration", no factorization) when
    ``options.exact_shortcut``; otherwise K is factorized. ``options.orthonormalize``
    projects the frames to rotations and solves again with them as soft targets (Sec. 4);
    ``options.refine`` fits the nearest surface when the linear answer does not reproduce
    the forms (:mod:`solver.refine`, started from :mod:`solver.linear.layout_fit`).

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
        weld_map: the forms' (n,) file vertex each file vertex was welded into (forms of a
            mesh with zero-length edges, :mod:`solver.mesh.weld`; with ``vertex_map``): a
            welded vertex gets its representative's position, ``report["input"]["weld"]``
            counts them.
        placement: the forms' component placement (:class:`solver.mesh.placement.Placement` or
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
    return reconstruct_on_cut(
        faces, edges, lengths, angles, constraints=constraints, options=options,
        n_vertices=n_vertices, layout_angles=layout_angles, initial_guess=initial_guess,
        progress=progress, vertex_map=vertex_map, placement=placement, weld_map=weld_map,
        **overrides)[0]


@dataclass(frozen=True)
class CutAnswer:
    """What :func:`reconstruct` solved before it placed the answer and mapped it to the file
    (for :func:`solver.differentiable.reconstruct_vjp`).

    Attributes:
        vertices: (n_cut, 3) float64 the answer on the solved (cut) mesh in the solver's
            gauge (anchored components: anchor vertex at the origin, anchor frame the
            identity), before placement, side-by-side layout and :meth:`ManifoldCut.to_file`.
        constraints: the validated constraints on the cut vertices (welded ones held by
            their representative).
        answer: the :class:`AnswerMap` that made the returned answer of ``vertices`` (the
            forms' cut, the placement applied to the unconstrained components, the
            components laid out side by side).
    """

    vertices: np.ndarray
    constraints: Constraints
    answer: AnswerMap


def reconstruct_on_cut(faces: ArrayLike, edges: ArrayLike, lengths: ArrayLike,
                       angles: ArrayLike, *, constraints: Constraints | None = None,
                       options: ReconstructOptions | None = None,
                       n_vertices: int | None = None, layout_angles: np.ndarray | None = None,
                       initial_guess: ArrayLike | None = None,
                       progress: Progress | None = None, vertex_map: ArrayLike | None = None,
                       placement: Placement | dict[str, Any] | None = None,
                       weld_map: ArrayLike | None = None,
                       **overrides: Any) -> tuple[Reconstruction, CutAnswer]:
    """:func:`reconstruct` (the same arguments and answer) and the :class:`CutAnswer` it
    placed and mapped to the file's vertices."""
    opts = ReconstructOptions.given(options, overrides)
    stages = Stages(progress)
    stages("validate")
    backend = resolve_backend(opts.backend or "auto")  # refused even when nothing factorizes
    cut = None
    if weld_map is not None and vertex_map is None:
        raise ConstraintError("weld_map needs the forms' vertex_map", field="weld_map")
    if vertex_map is not None:
        cut = ManifoldCut.from_vertex_map(vertex_map, faces, n_vertices, weld_map)
        n_vertices = cut.n_vertices
    topology, L, A = validate_forms(faces, edges, lengths, angles, n_vertices)
    place = Placement.coerce(placement, topology.n_faces)
    user = (constraints or Constraints()).validated(topology.n_vertices, topology.n_faces)
    if cut is not None and cut.weld_map is not None and len(user.position_vertices):
        # A constraint on a welded vertex holds its representative (one unknown): two on
        # one group are a repeated vertex (ConstraintError).
        held = user.position_vertices
        below = held < cut.n_file_vertices
        held = np.where(below, cut.weld_map[np.minimum(held, cut.n_file_vertices - 1)], held)
        user = replace(user, position_vertices=held).validated(topology.n_vertices,
                                                               topology.n_faces)
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

    method, refine_method = linear_methods(topology.n_faces, opts.linear_solver,
                                           opts.memory_budget)
    tree = _TreeStart(problem, touched) if method == "iterative" else None
    regularized: list[int] = []
    ref_v = np.zeros((topology.n_vertices, 3))
    pos_only, frame_only = problem.underdetermined_components(user)
    if len(pos_only) or len(frame_only):
        # The gauge left free by the constraints is pinned to an anchored reconstruction.
        stages("factorize")
        ref_anchor, _ = problem.anchors(np.ones_like(touched))
        ref_u = _system(problem, ref_anchor, backend, tree).solve(
            ref_anchor.hard_values, np.zeros((0, 3)), None if tree is None else tree.guess)
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
    solve_path = "tree-integration" if u is not None else (
        "iterative" if method == "iterative" else "factorization")
    factorized = {"backend": "none", "analysis": "none"}
    linear_solver = None
    refine = opts.refine
    # Forms that fail the check are refined: the iterative answer only starts it.
    tolerance = (LINEAR_SOLVER_RULES.start_tolerance if method == "iterative"
                 and refine is not False and known_not_integrable else None)
    system = None
    if u is None:
        stages("factorize")
        system = _system(problem, linear, backend, tree, release=not opts.orthonormalize)
        stages.lap("factorize")
        stages("solve")
        last = tree is not None and not opts.orthonormalize  # the tree start's last use
        guess = None if tree is None else (tree.handed_over() if last else tree.guess)
        if last:
            problem.release_transitions()  # the check's quaternions: rebuilt if used again
        u = system.solve(linear.hard_values, linear.soft_values, guess, tolerance,
                         overwrite_guess=last,
                         progress=stages.part("solve", 0.0, 0.5 if opts.orthonormalize else 1.0))
        del guess
        factorized = {"backend": system.backend, "analysis": system.analysis}
        linear_solver = system.linear_solver_report()
        stages.lap("solve")

    first_energy = problem.energies(u)
    vertices, frames = problem.unknowns_to_geometry(u, user)
    vertices = problem.recenter(vertices, user, ref_v)
    refinement: dict[str, Any] = not_refined("exact: tree integration")
    if solve_path != "tree-integration":
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
        if exact and tolerance is not None and system is not None:
            # Returned after all: solved on from the start's tolerance to the full one.
            u = system.solve(linear.hard_values, linear.soft_values, u)
            linear_solver, tolerance = system.linear_solver_report(), None
            first_energy = problem.energies(u)
            vertices, frames = problem.unknowns_to_geometry(u, user)
            vertices = problem.recenter(vertices, user, ref_v)
    # Dropped now, its analysis (the pattern of K) serves the orthonormalization's
    # factorization below: only the numerical phase is redone (solver.linalg's cache).
    del system
    energy = dict(first_energy)  # of the unknowns returned; redone if they change
    orthonormality = _orthonormality_error(frames)
    if opts.orthonormalize and solve_path != "tree-integration":  # integrated: rotations
        stages("factorize", 0.5)
        rotations = nearest_rotation(frames)
        cols = problem.all_frame_columns()
        system2 = _system(problem, linear, backend, tree, cols, opts.orthonormal_weight,
                          release=True)
        stages.lap("factorize")
        stages("solve", 0.5)
        targets = np.swapaxes(rotations, 1, 2).reshape(-1, 3)
        soft_values = np.concatenate([linear.soft_values, targets])
        u = system2.solve(linear.hard_values, soft_values, u, tolerance,
                          progress=stages.part("solve", 0.5))
        if system2.iterative is not None:
            linear_solver = {**system2.linear_solver_report(), "first_solve": linear_solver}
        vertices, frames = problem.unknowns_to_geometry(u, user)
        vertices = problem.recenter(vertices, user, ref_v)
        energy = problem.energies(u)
        stages.lap("solve")
    stages("solve", 1.0)
    if solve_path != "tree-integration" and refine is not False and not exact:
        # Nothing of Eq. 5's solves serves the refinement: its rows, K and the tree start's
        # guess and near-null space are let go before it builds its own matrices.
        problem.release_linear()
        tree = None
        stages("refine")
        vertices, refinement = _refined(problem, user, vertices, frames, anchored,
                                        initial_guess, opts, backend, stages, progress,
                                        refine_method)
        frames = problem.frames_of(vertices)
        stages.lap("refine")
        stages("refine", 1.0)

    input_report: dict[str, Any] = {"wrapped_angles": wrapped_angle_count(angles),
                                     "zero_area_faces": len(flat_faces(topology, L)),
                                     "placement": "none"}
    laid_out = np.array([a["component"] for a in anchored], dtype=np.int64)
    if place is None and len(laid_out) > 1:
        # No placement: the anchored parts would all sit at the origin (issue 40).
        input_report["placement"] = (f"none: {len(laid_out)} components laid out side by "
                                     "side along +x")
    if place is not None:
        moving = ~touched[topology.face_component[place.faces]]
        place = place.subset(moving)
        input_report["placement"] = f"{int(moving.sum())} of {len(moving)} components placed"
    answer = AnswerMap.of(topology, cut, place, laid_out if place is None else laid_out[:0])
    solved = CutAnswer(vertices=vertices, constraints=user, answer=answer)
    vertices, frames, spread = answer.forward(vertices, frames)
    isolated = topology.isolated_vertices
    if cut is not None:
        input_report.update(cut.sections(spread) or {"cut": cut.report(spread)})
        if cut.weld_map is not None:  # a welded vertex is no face's, yet not isolated
            below = isolated < cut.n_file_vertices
            welded = np.zeros(len(isolated), dtype=bool)
            welded[below] = cut.weld_map[isolated[below]] != isolated[below]
            isolated = isolated[~welded]
    report = ReconstructReport(
        energy=energy, first_solve_energy=first_energy,
        frame_orthonormality_error=orthonormality, orthonormalized=bool(opts.orthonormalize),
        refinement=refinement, timings=stages.timings, **factorized, solve_path=solve_path,
        n_unknowns=problem.n_unknowns, frame_weight=problem.frame_weight,
        weighting=problem.weighting, length_scale=problem.length_scale,
        regularized_components=regularized, anchored_components=anchored,
        isolated_vertices=isolated.tolist(), integrability=integrability,
        warnings=as_report(refinement_warnings(refinement)), input=input_report,
        linear_solver=linear_solver)
    return Reconstruction(vertices=vertices, frames=frames, report=report), solved


def _refined(problem: ImmersionProblem, user: Constraints, vertices: np.ndarray,
             frames: np.ndarray, anchored: list[dict[str, int]],
             initial_guess: ArrayLike | None, opts: ReconstructOptions, backend: str,
             stages: Stages, progress: Progress | None,
             method: str = "direct") -> tuple[np.ndarray, dict[str, Any]]:
    """The refinement of :func:`reconstruct`: vertices (n, 3) nearest to the forms, started
    from the better of the layout fit of the linear answer and ``initial_guess``, moved back
    to the anchors; and its report. ``method``: the linear solver its Gauss-Newton steps
    use (the one Eq. 5 used: ``"direct"`` or ``"iterative"``)."""
    topology = problem.topology
    start = problem.refinement_start(problem.layout_fit(user, backend), frames, user,
                                     vertices)
    targets = FormTargets(topology, problem.lengths, problem.angles,
                          angle_weight=opts.angle_weight)
    refiner = Refiner(targets, problem.refinement_handles(user), backend=backend,
                      linear_solver=method)
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


class _TreeStart:
    """The iterative path's start and near-null space: the unknowns integrated along spanning
    trees from every component's anchor (the anchors of :meth:`ImmersionProblem.anchors`,
    so the start satisfies them on the components without constraints)."""

    def __init__(self, problem: ImmersionProblem, touched: np.ndarray) -> None:
        self._problem, self._touched = problem, touched

    @functools.cached_property
    def guess(self) -> np.ndarray | None:
        """(N, 3) float64 tree-integrated unknowns (None if not finite); integrated on first
        use, so an answer of the tree integration alone never pays for it twice."""
        _, roots = self._problem.anchors(np.ones_like(self._touched))
        u = self._problem.tree_unknowns([a["face"] for a in roots],
                                        [a["vertex"] for a in roots])
        return u if bool(np.isfinite(u).all()) else None

    def handed_over(self) -> np.ndarray | None:
        """:attr:`guess` for a solve to overwrite, forgotten here with :attr:`near_null`
        (the system has its own copy of it): neither is held beside the solve's own
        arrays (224 MB at 1.6M faces)."""
        guess = self.guess
        self.__dict__.pop("guess", None)
        self.__dict__.pop("near_null", None)
        return guess

    def handed_over_near_null(self) -> np.ndarray | None:
        """:attr:`near_null` for the last system to use in place, forgotten here: not
        held beside the system's own (zeroed) copy through the multigrid setup; the
        problem's transition rotations and quaternions, whose last use was the guess's
        integration, are let go too (assembled again if used later)."""
        near_null = self.near_null  # integrates the guess first: the transitions' last use
        self.__dict__.pop("near_null", None)
        self._problem.release_transitions()  # not held through the setup (77 MB at 1.6M)
        return near_null

    @functools.cached_property
    def near_null(self) -> np.ndarray | None:
        """(N, 4) near-null space of K from :attr:`guess` (None if not finite)."""
        u = self.guess
        if u is None:
            return None
        # In the preconditioner's precision (the system takes a copy in it): half the bytes
        # held through the multigrid setup.
        return near_null_space(self._problem.topology.n_vertices, u).astype(
            LINEAR_SOLVER_RULES.preconditioner_dtype)


def _system(problem: ImmersionProblem, linear: Any, backend: str, tree: _TreeStart | None,
            extra_columns: np.ndarray | None = None, extra_weight: float = 0.0,
            release: bool = False) -> Any:
    """The constrained system of Eq. 5: factorized (``tree`` None) or iterative; ``release``
    for the last system :func:`reconstruct` builds (``problem.K`` is freed as soon as the
    system has its own constrained copy: :meth:`ImmersionProblem.system`)."""
    if tree is None:
        return problem.system(linear, backend, extra_columns, extra_weight, release=release)
    return problem.system(linear, backend, extra_columns, extra_weight, method="iterative",
                          near_null=tree.handed_over_near_null if release else tree.near_null,
                          release=release)


def _orthonormality_error(frames: np.ndarray) -> float:
    """max_t ||f_t^T f_t - I||_max: how far the solved frames are from rotations."""
    worst = 0.0
    for lo in range(0, len(frames), 1 << 16):  # blocks: temporaries of a few MB
        f = frames[lo:lo + (1 << 16)]
        for i in range(3):  # the Gram matrix's upper triangle, entry by entry
            for j in range(i, 3):
                gram = f[:, 0, i] * f[:, 0, j] + f[:, 1, i] * f[:, 1, j] + f[:, 2, i] * f[:, 2, j]
                gram -= float(i == j)
                worst = max(worst, float(np.abs(gram).max()))
    return worst
