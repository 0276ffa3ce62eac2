"""The nearest surface: a nonlinear fit of vertex positions to target fundamental forms.

The linear solve of Eq. (5) is exact for integrable forms. For forms that no surface has
(noisy, edited, blended or constrained ones) its frames are not rotations, so the answer
shrinks and distorts (Sec. 4 and 6 of the paper). This module returns, from a starting
embedding (the layout fit of the linear answer, :mod:`solver.linear.layout_fit`), the vertex
positions whose fundamental forms are nearest to the requested ones: the minimum of the
energy of :mod:`solver.refine.form_energy` (relative length errors, dihedral-angle errors, handle
terms), by Levenberg-Marquardt on the positions directly.

Each fresh step builds the Gauss-Newton matrix ``J^T J`` in its fixed block pattern
(:mod:`solver.refine.normal_equations`), damps it (``+ lambda diag``) and factorizes it with
:func:`solver.linalg.factorize`. Between factorizations the steps are quasi-Newton: L-BFGS
with that factor as its initial Hessian (Liu, Bouaziz and Kavan 2017, "Quasi-Newton methods
for real-time simulation of hyperelastic materials"), one back-substitution each, corrected
along the last steps by the gradients they produced; the factor is rebuilt at the current
positions when its steps stop lowering E as predicted. A session's drags keep the factor
from drag to drag. Steps are shortened by backtracking before the damping grows; a step is
kept only when it lowers ``E``, so the result is never worse than the start. Measurements
and the reasons for each choice: ``docs/refinement.md``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
from threadpoolctl import ThreadpoolController

from ..core.budget import Budget
from ..linalg import SingularSystemError, analyze, factorize, resolve_backend
from ..linalg.iterative import available_memory
from ..mesh.embedding_geometry import hinge_angles, hinges, signed_areas  # noqa: F401 - re-exported
from ..mesh.rigid_motions import RigidMotions, RigidProjection
from . import stopping
from .damping import damped
from .energy_weights import (  # noqa: F401 - re-exported: the refinement's public names
    ANGLE_WEIGHT,
    AREA_FLOOR,
    AREA_WEIGHT,
    DEFORM_ANGLE_WEIGHT,
    HARD_FRAME_WEIGHT,
)
from .form_energy import (  # noqa: F401 - re-exported: the refinement's public names
    FORMS_TOLERANCE,
    FormEnergy,
    FormTargets,
    Handles,
    form_residuals,
    form_weights,
    reproduces,
)
from .iteration_state import IterationState
from .iterative_steps import REFINEMENT_SOLVER_RULES, Multigrid
from .mixed_precision import ImpreciseSolveError, SinglePrecisionFactor
from .normal_equations import (  # noqa: F401 - re-exported
    PATTERN_CACHE_BYTES,
    GaussNewtonSystem,
    clear_pattern_cache,
    pattern_cache_info,
)
from .outcomes import with_outcome
from .steps import DEFAULT_STEP_RULES, StepRules, factor_precision, nielsen_damping
from .stopping import DEFAULT_STOP_RULES, StopReason, StopRules


@dataclass
class Refinement:
    """Result of :func:`refine`.

    Attributes:
        vertices: (n, dim) float64 refined positions (fixed vertices copied bit for bit).
        report: ``refined`` (bool), ``converged``, ``iterations``, ``rejected_steps``,
            ``factorizations`` (the factors computed, a float32 one that PARDISO refused not
            included) and their ``precision`` (``"single"``, ``"double"``, or ``"mixed"``
            where single precision was given up during the run: :func:`factor_precision`),
            ``solves`` (back-substitutions, a single-precision solve's refinement step's
            included),
            ``seconds``, ``energy_before`` / ``energy_after``, ``before`` / ``after`` residual
            summaries (:func:`form_residuals`), ``stop_reason``, ``outcome`` and
            ``outcome_text`` (:mod:`solver.refine.outcomes`: converged, partial or not refined).
    """

    vertices: np.ndarray
    report: dict[str, Any]


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
        stop_rules: when a run stops (:class:`~solver.refine.stopping.StopRules`).
        step_rules: how it steps (:class:`~solver.refine.steps.StepRules`).
        linear_solver: ``"direct"`` (default: each fresh step factorizes), ``"iterative"``
            (inexact Gauss-Newton steps by multigrid-preconditioned CG, no factor:
            :mod:`solver.refine.iterative_steps`) or ``"auto"``/None (by size and memory:
            :data:`solver.refine.iterative_steps.REFINEMENT_SOLVER_RULES`).
        memory_budget: bytes ``auto`` chooses by (``iterative.available_memory``).
    """

    def __init__(self, targets: FormTargets, handles: Handles | None = None, dim: int = 3,
                 backend: str = "auto", *, stop_rules: StopRules = DEFAULT_STOP_RULES,
                 step_rules: StepRules = DEFAULT_STEP_RULES,
                 linear_solver: str | None = "direct",
                 memory_budget: float | None = None) -> None:
        handles = handles or Handles(soft_positions=np.zeros((0, dim)),
                                     frame_edges=np.zeros((0, 2, dim)))
        self.targets = targets
        self.backend = backend
        self.stop_rules, self.step_rules = stop_rules, step_rules
        self.form_energy = FormEnergy(targets, handles, dim)
        self.system = GaussNewtonSystem(self.form_energy)
        energy = self.form_energy
        self.rigid_motions = RigidMotions(targets.topology, energy.free, energy.held, dim)
        self._needle_coordinates = self._needles()
        self.linear_solver = REFINEMENT_SOLVER_RULES.choose(
            targets.topology.n_faces, linear_solver, available_memory(memory_budget))
        self._multigrid = (Multigrid.of(step_rules) if self.linear_solver == "iterative"
                           else None)
        # The factor, its matrix and the projection off its rigid motions that the previous
        # keep_factor run ended with (see run(keep_factor=True)).
        self._kept: tuple[Any, sp.csr_array, RigidProjection] | None = None
        self._kept_damping = step_rules.initial_damping
        self._double = False  # a single-precision factor was too inexact: double from now on
        self._paused: IterationState | None = None  # a run stopped at its time limit (resume)
        self._iteration_seconds: dict[str, float | None] = {"refresh": None, "step": 0.0}
        """Seconds of the last iteration with a factorization and without (the time limit
        stops before an iteration that would end past it); None: no factorization timed or
        estimated yet (:meth:`expect_refresh`)."""

    def _needles(self) -> np.ndarray:
        """(k,) int64 the unknowns of the needle edges' free vertices (capped damping:
        :func:`solver.refine.damping.damped`)."""
        dim = self.system.dim
        index = self.system.index[self.form_energy.needle_vertices]
        index = index[index >= 0]
        return (index[:, None] * dim + np.arange(dim)).ravel()

    def retarget(self, targets: FormTargets) -> bool:
        """Replace the target forms (lengths, angles, weights) in place for the next
        :meth:`run`: the residual groups' structure, the Gauss-Newton pattern, the rigid
        motions and the kept factor stay, only the values change (the rows of a blend
        sequence, :func:`solver.blend`). Returns False, changing nothing, where ``targets``
        have another structure (:meth:`FormEnergy.retarget`: other needle ties or cap
        faces, another topology): build a new refiner then (:meth:`adopt_factor` passes
        it the factor where the patterns agree). A run stopped at its time limit can no
        longer be resumed."""
        if not self.form_energy.retarget(targets):
            return False
        self.targets = targets
        self._needle_coordinates = self._needles()
        self._paused = None
        return True

    def set_handle_targets(self, soft_positions: np.ndarray | None = None,
                           frame_edges: np.ndarray | None = None) -> None:
        """Replace the soft handle positions (p, dim) and the orientation handles' target
        edge vectors (q, 2, dim) (``None`` keeps the current ones)."""
        self.form_energy.set_handle_targets(soft_positions, frame_edges)

    def energy(self, vertices: np.ndarray) -> float:
        """E of (n, dim) positions (fixed vertices as given; tied vertices, the endpoints of
        needles, where a run started there puts them: :mod:`solver.refine.ties`)."""
        energy = self.form_energy
        return energy.energy(energy.placed(np.asarray(vertices, dtype=np.float64), own=True))

    def reproduces(self, vertices: np.ndarray) -> bool:
        """Whether ``vertices`` already have the target forms (:func:`reproduces`)."""
        t = self.targets
        return reproduces(vertices, t.topology, t.lengths, t.angles, self.form_energy.hinges)

    def residuals(self, vertices: np.ndarray) -> dict[str, Any]:
        """:func:`form_residuals` of ``vertices`` against the targets."""
        t = self.targets
        return form_residuals(vertices, t.topology, t.lengths, t.angles,
                              self.form_energy.hinges)

    def run(self, start: np.ndarray, *, soft_positions: np.ndarray | None = None,
            frame_edges: np.ndarray | None = None, max_iterations: int | None = None,
            tolerance: float | None = None, time_limit: Budget | float | None = None,
            keep_factor: bool = False, progress: Any = None,
            start_energy: float | None = None, interactive: bool | None = None,
            ) -> Refinement:
        """Refine from ``start`` (n, dim); fixed vertices keep their ``start`` positions.

        ``soft_positions`` (p, dim) and ``frame_edges`` (q, 2, dim) replace the handle
        targets given at construction. ``keep_factor``: start from the factorization the
        previous ``keep_factor`` run ended with and keep this run's for the next (for a
        session's drags, which are alike); convergence may then be declared on a
        quasi-Newton step of that kept factor, without a fresh factorization to confirm it.
        ``time_limit``: a :class:`~solver.core.budget.Budget`, or seconds from now; a run that
        stops at it can be continued by :meth:`resume`.
        ``start_energy``: :meth:`energy` of ``start`` with these handle targets, when the
        caller has it. ``interactive`` (default: ``keep_factor``): convergence may be
        declared on a step of a kept factor without the checks a one-shot refinement makes
        (a session's drags); ``keep_factor=True, interactive=False`` keeps factors from run
        to run but converges as a one-shot refinement does (the rows of a blend sequence,
        :func:`solver.blend`, whose answers are compared with independent ones). See
        :func:`refine` for the rest (``max_iterations`` and ``tolerance`` replace those of
        this refiner's :class:`~solver.refine.stopping.StopRules`).
        """
        clock = time.perf_counter()
        self.set_handle_targets(soft_positions, frame_edges)
        given = {"max_iterations": max_iterations, "tolerance": tolerance}
        rules = replace(self.stop_rules, **{k: v for k, v in given.items() if v is not None})
        with _BLAS.limit(limits=1, user_api="blas"):
            X = np.array(start, dtype=np.float64)
            self.form_energy.tie(X)  # needles' tied vertices on their target lengths
            # The start's energy and residuals come with the first iteration's evaluation
            # at X (one pass over the mesh, not two): IterationState.measured.
            state = IterationState.start(X, start_energy, self._kept, self._kept_damping,
                                         keep_factor, rules, self.step_rules)
            state.interactive = keep_factor if interactive is None else interactive
            if self._multigrid is not None:  # every step fresh: an assembly costs less
                state.max_frozen = 1         # than a CG solve on an old matrix
                self._multigrid.reset_stats()
            return self._advance(state, Budget.of(time_limit), progress, clock)

    def adopt_factor(self, other: Refiner) -> bool:
        """Take the factor (and its damping) that ``other``'s last ``keep_factor`` run kept,
        as this refiner's first model for its next ``keep_factor`` run: rows of a blend
        sequence have other targets but, with the same residuals' pattern, the Gauss-Newton
        matrix of a nearby shape (:func:`solver.blend`). Returns whether it was taken (not
        where the patterns differ, e.g. other cap faces, or ``other`` kept none)."""
        mine, theirs = self.system, other.system
        same = (other._kept is not None and mine.n_free == theirs.n_free
                and mine.dim == theirs.dim and mine.nnz == theirs.nnz
                and np.array_equal(mine.indptr, theirs.indptr)
                and np.array_equal(mine.indices, theirs.indices))
        if same:
            self._kept, self._kept_damping = other._kept, other._kept_damping
            self._double = other._double
            self._iteration_seconds = dict(other._iteration_seconds)
        return same

    @property
    def can_resume(self) -> bool:
        """Whether the last run stopped at its time limit and :meth:`resume` continues it."""
        return self._paused is not None

    def resume(self, time_limit: Budget | float | None = None, progress: Any = None,
               ) -> Refinement:
        """Continue the last :meth:`run` that stopped at its ``time_limit`` for up to
        ``time_limit`` more seconds, exactly as if it had not been interrupted (the same
        damping, factor, quasi-Newton memory and counters): slices of a refinement end
        where one uninterrupted run ends. The report counts the whole refinement, and
        ``slices`` the calls so far; ``seconds`` is this call's. Raises ``RuntimeError``
        when there is nothing to resume (another run, or a finished one, came since)."""
        state, self._paused = self._paused, None
        if state is None:
            raise RuntimeError("no refinement stopped at its time limit to resume")
        clock = time.perf_counter()
        with _BLAS.limit(limits=1, user_api="blas"):
            state.slices += 1
            return self._advance(state, Budget.of(time_limit), progress, clock)

    def _advance(self, state: IterationState, budget: Budget, progress: Any,
                 clock: float) -> Refinement:
        """Iterate ``state`` until it stops (:meth:`_iterate`); the :class:`Refinement`."""
        self._paused = None
        notify = _IterationNotifier(progress, budget)
        if self._multigrid is None:
            self._iterate(state, budget, notify, clock)
        else:  # the CG solves report their progress within a step
            self._multigrid.progress = notify.solving if progress is not None else None
            try:
                self._iterate(state, budget, notify, clock)
            finally:
                self._multigrid.progress = None
        if state.before is None:  # stopped before a first evaluation: measure the start
            state.measured(self.form_energy.energy(state.X), self.form_energy.report(state.X))
        if state.stop == StopReason.TIME_LIMIT:
            self._paused = state
        if state.keep_factor and state.factor is not None:
            self._kept = (state.factor, state.model, state.projection)
            self._kept_damping = state.damping
        solver = ({"method": "direct"} if self._multigrid is None else
                  self._multigrid.stats.report(self.step_rules.cg_max_iterations))
        return Refinement(vertices=state.X.copy(), report=with_outcome({
            "refined": True, **state.counters(), "after": self.form_energy.report(state.X),
            "linear_solver": solver,
            "angle_weight": self.targets.angle_weight,
            "seconds": time.perf_counter() - clock}))

    def _iterate(self, s: IterationState, budget: Budget, notify: Any, clock: float) -> None:
        """The iteration of :meth:`run` and :meth:`resume`, advancing ``s`` in place until
        a rule of :mod:`solver.refine.stopping` stops it or ``budget`` runs out (it stops before an
        iteration or a factorization that the last one of its kind says would end past
        it)."""
        system, rules, steps = self.system, s.rules, self.step_rules
        s.stop = None
        while not s.converged:
            reason = stopping.out_of_budget(rules, s.iterations, system.n_free)
            if reason is not None:
                s.end(reason)
                break
            refresh = s.factor is None or s.frozen_steps >= s.max_frozen
            if not self._fits(s, refresh, budget):
                s.end(StopReason.TIME_LIMIT)
                break
            began, refreshed = time.perf_counter(), False
            s.iterations += 1
            if refresh and self._multigrid is not None and not s.keep_factor:
                # Replaced below by this point's: the last operator's and model's matrices
                # are let go before the new one is assembled (the refinement's peak by CG).
                s.factor = s.model = None
            energy, H, g = system.normal_equations(s.X, matrix=refresh)
            if s.before is None:  # the start, measured by this evaluation
                s.measured(energy, self.form_energy.report(s.X))
            s.memory.observe(g)
            if stopping.exact(rules, energy):
                s.end(StopReason.EXACT)
                break
            accepted = False
            while not accepted and not stopping.stationary(rules, s.damping):
                if refresh:
                    s.factor = None  # frees its analysis for the cache: the next one reuses it
                    s.projection = self.rigid_motions.at(s.X[self.form_energy.free])
                    try:
                        s.factor = self._damped_factor(H, s.damping, not s.keep_factor, s, g)
                    except SingularSystemError:
                        s.damping, s.rejected = s.damping * 10.0, s.rejected + 1
                        continue
                    refreshed = True
                    if self._multigrid is None:
                        s.factorizations += 1
                        s.precisions.add(s.factor.precision)
                    s.model, s.fresh, s.frozen_steps, s.factor_gain = H, True, 0, 0.0
                    s.memory.clear()
                s.solves += 1
                try:
                    step, slope, predicted = s.direction(g, system)
                except ImpreciseSolveError:
                    # A single-precision factor too inexact here (or a float32 answer that
                    # is not finite): this refiner factorizes in double from now on, here
                    # first, as after a refused step (its time limit included).
                    self._double = True
                    if self._refresh_stopped(s, budget):
                        break
                    if H is None:
                        energy, H, g = system.normal_equations(s.X)
                    refresh = True
                    continue
                except SingularSystemError:
                    # The backend's solve is inaccurate (a factor of an ill-conditioned
                    # matrix: needles and slivers, issue 40): more damping, a new factor.
                    s.damping, s.rejected = s.damping * 10.0, s.rejected + 1
                    if H is None:
                        energy, H, g = system.normal_equations(s.X)
                    refresh = True
                    continue
                found = self._line_search(s.X, step, energy, slope) if slope < 0 else None
                gained = energy - found[2] if found is not None else 0.0
                if (found is not None and not s.fresh and not s.interactive
                        and gained < steps.frozen_gain * predicted):
                    # A step of a factor built elsewhere that lowers E by less than half its
                    # prediction went astray: a fresh step from here does better.
                    found = None
                accepted = found is not None
                moved = float(np.abs(step).max(initial=0.0)) / system.energy.scale
                negligible = stopping.negligible(
                    rules, fresh=s.fresh,
                    trusted=stopping.trusted(rules, s.damping, s.factor_gain),
                    interactive=s.interactive, moved=moved, predicted=predicted,
                    energy=energy, refused=found is None, gained=gained)
                if found is None:
                    s.rejected += 1
                    if negligible:
                        s.end(StopReason.CONVERGED)
                        break
                    if s.fresh:
                        s.damping = max(s.damping * s.growth, steps.refused_damping)
                        s.growth *= 2.0
                    if self._refresh_stopped(s, budget):
                        break
                    if not s.fresh and H is None:  # a kept factor failed: rebuild it here
                        energy, H, g = system.normal_equations(s.X)
                    refresh = True
                    continue
                alpha, trial, new_energy = found
                s.memory.moved(alpha * step, g, system, s.model)
                gain = (energy - new_energy) / predicted if predicted > 0 else 0.0
                decrease, s.X, s.energy = energy - new_energy, trial, new_energy
                energy = new_energy
                s.trace.append(energy)
                s.steps.append(moved)
                notify(s.iterations, s.factorizations, energy, time.perf_counter() - clock)
                verdict = stopping.after_step(
                    rules, fresh=s.fresh, interactive=s.interactive, alpha=alpha,
                    damping=s.damping, gain=gain, moved=moved, decrease=decrease,
                    energy=energy, negligible=negligible, frozen_steps=s.frozen_steps,
                    exact_solve=self._multigrid is None or s.factor.tolerance <= steps.cg_confirm)
                if verdict == stopping.CONFIRM:
                    s.frozen_steps, s.confirm = s.max_frozen, self._multigrid is not None
                elif verdict is not None:
                    s.end(verdict)
                if s.fresh:  # Levenberg-Marquardt's damping update (Nielsen)
                    s.damping = nielsen_damping(steps, s.damping, gain, alpha)
                    s.growth = 2.0
                # The next steps reuse this factor (quasi-Newton, one back-substitution each)
                # while they lower E about as predicted; otherwise it is rebuilt at the new X,
                # as it is (unless it was kept) after a long step.
                s.fresh, s.factor_gain = False, gain
                s.frozen_steps += 1
                if gain < s.min_gain or (moved > steps.frozen_reach and not s.kept):
                    s.frozen_steps = s.max_frozen
            if s.stop == StopReason.TIME_LIMIT:
                break
            kind = "refresh" if refreshed else "step"
            self._iteration_seconds[kind] = time.perf_counter() - began
            if not s.converged:
                reason = stopping.after_iteration(rules, accepted, s.trace, s.steps)
                if reason is not None:
                    s.end(reason)
                    if reason in (StopReason.STALLED, StopReason.CONVERGED):
                        break

    def prepare(self) -> None:
        """Have the factorization backend analyse the Gauss-Newton matrix's pattern now
        (PARDISO's ordering and symbolic factorization, cached per pattern: they depend on
        the pattern only), so that the first factorization of a later interactive run
        (``keep_factor``, factorized in double precision) pays only its numerical phase: a
        session's first refined drag, whose frame budget would otherwise go to the
        analysis (:class:`solver.deform.Deformer` calls it at set-up)."""
        system = self.system
        if system.n_free:
            n = system.n_free * system.dim
            pattern = sp.csr_array((np.zeros(system.nnz), system.indices, system.indptr),
                                   shape=(n, n))
            pattern.has_canonical_format = True
            analyze(pattern, self.backend)

    def expect_refresh(self, seconds: float) -> None:
        """Estimate the seconds of an iteration with a factorization (the Gauss-Newton
        matrix's assembly and factorization) before this refiner has timed one, e.g. from
        the factorization of the linear answer, which costs about as much: a time limit
        then also stops before the first factorization of a run if it would end past it
        (a request's deadline is then not overrun by a factorization begun just before it
        ends). Without an estimate the first factorization starts while any time is left,
        so that a budget shorter than one still progresses (a session's slices)."""
        if self._iteration_seconds["refresh"] is None and seconds > 0:
            self._iteration_seconds["refresh"] = float(seconds)

    def _fits(self, s: IterationState, refresh: bool, budget: Budget) -> bool:
        """Whether an iteration (a factorization first where ``refresh``) ends before
        ``budget`` runs out, judged by the last one of its kind (or by
        :meth:`expect_refresh`'s estimate; with neither it starts while time is left)."""
        left = budget.left()
        if left is None:
            return True
        kind = "refresh" if refresh or s.factor is None else "step"
        return left > (self._iteration_seconds[kind] or 0.0)

    def _refresh_stopped(self, s: IterationState, budget: Budget) -> bool:
        """Whether the factorization that the iteration of ``s`` needs now would end past
        ``budget``: then the run stops here (``time_limit``), and a resumed run starts
        this iteration again with that factorization."""
        if self._fits(s, True, budget):
            return False
        s.frozen_steps = s.max_frozen
        s.end(StopReason.TIME_LIMIT)
        s.iterations -= 1
        return True

    def _damped_factor(self, H: sp.csr_array, damping: float, single: bool = False,
                       s: IterationState | None = None, g: np.ndarray | None = None) -> Any:
        """Factorization of ``H`` damped by ``damping`` (:func:`solver.refine.damping.damped`).
        Raises :class:`SingularSystemError` where the backend finds it singular. On the
        iterative path, its CG solver instead (:mod:`solver.refine.iterative_steps`), whose
        tolerance is the forcing term of the gradient ``g`` at ``s``'s positions (both
        required there; the direct path reads neither).

        PARDISO orders this matrix itself (no ``groups`` hint): that keeps its two-level
        factor (docs/refinement.md). It factorizes in single precision where ``single``
        asks for it and the diagonal allows (:func:`factor_precision`), and in double from
        the first time single precision finds the matrix not positive definite or one of
        its solves too inexact (:meth:`_iterate`). Interactive runs (``keep_factor``)
        factorize in double: their factors serve many solves, each of which single
        precision makes three times as costly, and a session's pattern is analysed ahead
        of time in one precision (:meth:`prepare`)."""
        positions = self.system.diagonal_positions
        matrix = damped(H, damping, positions, self._needle_coordinates)
        if self._multigrid is not None:
            if s is None or g is None:
                raise ValueError("the iterative path's step needs the state and gradient")
            operator = self._multigrid.operator(matrix, s.X[self.form_energy.free],
                                                s.projection)
            operator.tolerance = s.forcing_for(g, self.step_rules)
            return operator
        if (single and not self._double and resolve_backend(self.backend) == "pardiso"
                and factor_precision(matrix.data[positions],
                                     self.step_rules.single_precision_spread) == "single"):
            try:
                return SinglePrecisionFactor(matrix, self.backend,
                                             self.step_rules.single_precision_error)
            except SingularSystemError:
                self._double = True
        return factorize(matrix, self.backend, triangle="upper")

    def _line_search(self, X: np.ndarray, step: np.ndarray, energy: float, slope: float,
                     ) -> tuple[float, np.ndarray, float] | None:
        """Backtracking along ``step`` (n_free * dim,) from ``X`` (n, dim) at energy
        ``energy`` with directional derivative ``slope`` < 0: the first of
        :attr:`StepRules.step_fractions` that decreases E sufficiently (Armijo), as
        ``(fraction, new positions, new E)``, or None. It costs energies, never
        factorizations."""
        free, dim = self.form_energy.free, self.form_energy.dim
        armijo = self.step_rules.armijo
        for alpha in self.step_rules.step_fractions:
            trial = X.copy()
            trial[free] += alpha * step.reshape(-1, dim)
            self.form_energy.place_tied(trial)  # tied vertices follow their masters
            new_energy = self.form_energy.energy(trial)
            if np.isfinite(new_energy) and new_energy < energy + armijo * alpha * slope:
                return alpha, trial, new_energy
        return None


_BLAS = ThreadpoolController()
"""The refinement's vectors are too short for a multithreaded BLAS to pay: on a loaded
machine its threads cost ~20 ms per dot product (docs/refinement.md), so :meth:`Refiner.run`
limits BLAS to one thread while it iterates."""


class _IterationNotifier:
    """``notify(iteration, factorizations, energy, seconds)`` for :meth:`Refiner.run`:
    calls ``progress("refine", fraction)`` and, when ``progress`` has one,
    ``progress.iteration(detail)``; does nothing without ``progress``. :meth:`solving`
    reports the progress within a step, as its CG solve goes (the iterative path).

    A refinement's length is unknown: most end after 2-5 iterations, so the fraction
    climbs towards 1 as iterations pass, ``done / (done + 3)`` with ``done`` the accepted
    steps plus the share of the solve under way (or as the time budget is spent); it never
    goes back, and within a step it is reported when it has grown by 0.01 or more."""

    step = 0.01

    def __init__(self, progress: Any, budget: Budget) -> None:
        self._progress = progress
        self._budget = budget
        self._detail = None if progress is None else getattr(progress, "iteration", None)
        self._iterations = 0
        self._reported = 0.0

    def __call__(self, iteration: int, factorizations: int, energy: float,
                 seconds: float) -> None:
        if self._progress is None:
            return
        self._iterations = iteration
        self._report(float(iteration), 0.0)
        if self._detail is not None:
            self._detail({"iteration": iteration, "factorizations": factorizations,
                          "energy": energy, "seconds": seconds})

    def solving(self, share: float) -> None:
        """The solve under way has done ``share`` (0 to 1) of its work."""
        if self._progress is not None:
            self._report(self._iterations + min(max(share, 0.0), 1.0), self.step)

    def _report(self, done: float, step: float) -> None:
        fraction = done / (done + 3.0)
        if self._budget.seconds:
            fraction = max(fraction, self._budget.spent() / self._budget.seconds)
        fraction = min(fraction, 0.99)
        if fraction < self._reported + step or (step and fraction <= self._reported):
            return
        self._reported = fraction
        self._progress("refine", fraction)


def refine(vertices: np.ndarray, targets: FormTargets, handles: Handles | None = None, *,
           max_iterations: int | None = None, tolerance: float | None = None,
           time_limit: Budget | float | None = None, backend: str = "auto",
           progress: Any = None, stop_rules: StopRules = DEFAULT_STOP_RULES,
           step_rules: StepRules = DEFAULT_STEP_RULES,
           linear_solver: str | None = "direct",
           memory_budget: float | None = None) -> Refinement:
    """Vertex positions whose fundamental forms are nearest to ``targets`` (Levenberg-Marquardt).

    Args:
        vertices: (n, dim) float64 start (dim 3, or 2 for a planar fit), e.g. the linear
            answer of Eq. (5). Fixed handle vertices keep these positions.
        targets: :class:`FormTargets` (lengths, angles, weights).
        handles: optional :class:`Handles`.
        max_iterations: Gauss-Newton matrices built (each one factorization, plus one per
            rejected step); None: ``stop_rules.max_iterations``.
        tolerance: stop after a full Gauss-Newton step that moved no vertex by more than
            ``tolerance`` times the mean target edge length; None: ``stop_rules.tolerance``.
        time_limit: optional :class:`~solver.core.budget.Budget` (or seconds from now): the
            refinement stops before an iteration (or a factorization) that, timed like the
            last one of its kind by this :class:`Refiner`, would end past it (the first
            factorization of a run that has none starts while time is left). It returns
            the best iterate, ``converged`` False and ``stop_reason`` ``"time_limit"``.
        backend: sparse factorization backend (:func:`solver.linalg.factorize`).
        progress: optional ``progress(stage, fraction)`` callback, called as
            ``progress("refine", fraction)`` after every accepted step; if it also has a
            method ``iteration(detail)``, that gets ``{"iteration", "factorizations",
            "energy", "seconds"}`` of each step (the service's job progress shows them).
        stop_rules: :class:`~solver.refine.stopping.StopRules` (when it stops).
        step_rules: :class:`~solver.refine.steps.StepRules` (how it steps).
        linear_solver, memory_budget: the Gauss-Newton steps' solver and the memory
            ``auto`` chooses it by (:class:`Refiner`).
    Returns:
        :class:`Refinement`. Its energy is never above the start's: a step is accepted
        only when it lowers E. ``report["converged"]`` is False when the iteration or time
        budget ran out first.

    Example::

        >>> import numpy as np, solver
        >>> from solver.refine import FormTargets, refine
        >>> from solver.mesh.topology import build_topology
        >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.2]])
        >>> F = np.array([[0, 1, 2], [2, 1, 3]])
        >>> forms = solver.fundamental_forms(V, F)
        >>> fit = refine(V * 0.9, FormTargets(build_topology(F), forms.lengths, forms.angles))
        >>> bool(fit.report["after"]["length_error"]["max"] < 1e-6)
        True
    """
    dim = np.shape(vertices)[1]
    return Refiner(targets, handles, dim, backend, stop_rules=stop_rules,
                   step_rules=step_rules, linear_solver=linear_solver,
                   memory_budget=memory_budget).run(
        vertices, max_iterations=max_iterations, tolerance=tolerance, time_limit=time_limit,
        progress=progress)
