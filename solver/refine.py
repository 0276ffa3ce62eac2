"""The nearest surface: a nonlinear fit of vertex positions to target fundamental forms.

The linear solve of Eq. (5) is exact for integrable forms. For forms that no surface has
(noisy, edited, blended or constrained ones) its frames are not rotations, so the answer
shrinks and distorts (Sec. 4 and 6 of the paper). This module returns, from a starting
embedding (the layout fit of the linear answer, :mod:`solver.layout_fit`), the vertex
positions whose fundamental forms are nearest to the requested ones: the minimum of the
energy of :mod:`solver.form_energy` (relative length errors, dihedral-angle errors, handle
terms), by Levenberg-Marquardt on the positions directly.

Each fresh step builds the Gauss-Newton matrix ``J^T J`` in its fixed block pattern
(:mod:`solver.normal_equations`), damps it (``+ lambda diag``) and factorizes it with
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
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from threadpoolctl import ThreadpoolController

from .form_energy import (  # noqa: F401 - re-exported: the refinement's public names
    ANGLE_WEIGHT,
    AREA_FLOOR,
    AREA_WEIGHT,
    DEFORM_ANGLE_WEIGHT,
    FORMS_TOLERANCE,
    HARD_FRAME_WEIGHT,
    FormEnergy,
    FormTargets,
    Handles,
    form_residuals,
    form_weights,
    hinge_angles,
    hinges,
    reproduces,
    signed_areas,
)
from .linalg import SingularSystemError, analyze, factorize, resolve_backend
from .mixed_precision import ImpreciseSolveError, SinglePrecisionFactor
from .normal_equations import (  # noqa: F401 - re-exported
    PATTERN_CACHE_BYTES,
    GaussNewtonSystem,
    clear_pattern_cache,
    pattern_cache_info,
)
from .outcomes import with_outcome
from .quasi_newton import QuasiNewtonMemory
from .rigid_motions import RigidMotions, RigidProjection

MAX_ITERATIONS = 50
TOLERANCE = 1e-4
"""Stop after a full Gauss-Newton step that moved no vertex by more than this fraction of
the mean target edge length (an energy criterion fails here: where the forms conflict, E
stays large at the optimum, so its relative decrease says little about the positions)."""
ENERGY_TOLERANCE = 1e-3
"""... or lowered E by less than this fraction of E (the slow tail of Gauss-Newton where
large residuals remain, e.g. strong deformations: measured to change the result's mean
length and angle errors in the fourth digit)."""
STALL_STEPS = 5
"""A run whose last this many steps together lowered E by at most :data:`ENERGY_TOLERANCE`
of it stops, not converged (``stop_reason: "stalled"``): it crawls on steps the damping has
shortened to nothing, which then can no longer prove convergence (a knight with 5 faces
flattened to 1e-6 of their width and 10 needle edges: the damping grew to 20, and 25 more
iterations lowered E by 0.2% before the iteration budget ran out)."""
EXACT_ENERGY = 1e-24  # E below this: the forms are met to round-off
STEP_FRACTIONS = (1.0, 0.5, 0.25, 0.1)  # of a Gauss-Newton step tried before more damping
ARMIJO = 1e-4  # sufficient decrease: E(x + a d) < E(x) + ARMIJO a g.d
MAX_FROZEN_STEPS = 6  # steps on one factorization before it is rebuilt at the current X
FROZEN_GAIN = 0.5  # rebuild earlier when a step lowers E by less than this x its prediction
FROZEN_REACH = 0.5  # ... or moved a vertex by more than this many mean edge lengths
QUASI_NEWTON_REACH = 1e-2
"""A refinement that is not interactive ends on a step of a factor built elsewhere (frozen
Gauss-Newton or L-BFGS) only if that step moved no vertex by more than this fraction of the
mean target edge length: where the valley of E is flat, its decrease is below
:data:`ENERGY_TOLERANCE` long before the positions settle (angles x 0.8 on the bunny: the
answer was 5.5e-4 of its size from the exact optimum without this, 6e-5 with it;
``python -m bench.refinement --sections optimum``)."""
REFUSED_PREDICTION = 2.0
"""A kept factor's step that is refused after gaining at most :data:`ENERGY_TOLERANCE` of E
at the best length tried still ends a run that is not interactive (converged) where the
factor predicted at most this many times :data:`ENERGY_TOLERANCE` of E: the model of a
nearby point overestimates what is left, and its best direction finds none of it
(nefertiti, noisy angles, min angle 0.06°: its prediction was 1.02e-3 of E and its step
gained nothing; 1 factorization instead of 2, 1.5e-5 of the size from the exact optimum
instead of 2.6e-7, the same 3.4e-5 from the original mesh). Not in a session's drags: their
kept factors come from other shapes (a pause's refinement stopped at a mean length change
of 0.0183 instead of 0.0158 with it)."""
SMALL_FROZEN_STEPS = 2
"""A factor takes at most this many further steps after a small, well-predicted one of its
own that moved more than :data:`QUASI_NEWTON_REACH` before a fresh factorization confirms
convergence (cactus x 0.8: two such steps of 1.1e-2 and 1.2e-2 of an edge, then one of
1.6e-3 that converged; 2 factorizations instead of 3). Fewer than :data:`STALL_STEPS`:
steps continued this way cannot end a run as stalled."""
KEPT_STEPS = 20
"""A run that starts from a kept factor (``keep_factor``: a session's drags after the
first) keeps it for up to this many quasi-Newton steps, rebuilding it only when a step
lowers E by less than :data:`KEPT_GAIN` x its prediction, and not after long steps: a
drag's factor comes from the previous drag's shape, and L-BFGS absorbs the difference
(rocker-arm, drags 2-5: no factorization instead of 17, and a lower final energy;
docs/refinement.md). Runs that factorize first (one-shot deformations, a session's first
drag) keep the stricter rules above, measured better there (the Botsch-Sorkine cases)."""
KEPT_GAIN = 0.05
KEPT_DAMPING = 1e-3
"""... provided the kept factor's relative damping is at most this: a heavily damped factor
(a hard previous drag ends at lambda ~ 1-10) takes short, well-predicted steps that would
keep it for ever while E falls by 1-3% a step (icosphere, 4 handles: 50 iterations, not
converged)."""
QUASI_NEWTON_MEMORY = 8
"""(s, y) pairs of L-BFGS since the factor was built, in runs that start from a kept factor
(elsewhere the steps between factorizations are plain frozen Gauss-Newton steps: L-BFGS
cost the cylinder of the Botsch-Sorkine cases 13 factorizations instead of 10)."""
INITIAL_DAMPING = 1e-9
"""lambda of the first step, relative to diag(J^T J): a plain Gauss-Newton step. A larger
start (1e-4 before) holds back the soft bending modes, whose curvature is far below the
stretching diagonal: each step then closed only a small fraction of their gap, and the
refinement crawled through a long tail of iterations (rocker-arm, noisy angles: 16
iterations and 4 factorizations against 2 and 1 to a lower energy; docs/refinement.md)."""
MIN_DAMPING = 1e-12  # the Nielsen update never lowers lambda below this
REFUSED_DAMPING = 1e-4  # at least this lambda after a fresh step that no backtracking saved
MAX_DAMPING = 1e12  # relative damping at which a step is declared impossible
SINGLE_PRECISION_SPREAD = 1e4
"""Largest spread (largest over median entry) of the damped Gauss-Newton matrix's diagonal
that is factorized in single precision (:func:`factor_precision`)."""
SINGLE_PRECISION_ERROR = 0.1
"""Largest relative correction of a single-precision factor's solve by its refinement step
before the refinement factorizes in double precision instead (the beetle's soft rims:
0.12-0.58; rocker-arm, the bunny: ~1e-3; armadillo, nefertiti: 2-4e-2)."""

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
            ``outcome_text`` (:mod:`solver.outcomes`: converged, partial or not refined).
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
    """

    def __init__(self, targets: FormTargets, handles: Handles | None = None, dim: int = 3,
                 backend: str = "auto") -> None:
        handles = handles or Handles(soft_positions=np.zeros((0, dim)),
                                     frame_edges=np.zeros((0, 2, dim)))
        self.targets = targets
        self.backend = backend
        self.form_energy = FormEnergy(targets, handles, dim)
        self.system = GaussNewtonSystem(self.form_energy)
        energy = self.form_energy
        self.rigid_motions = RigidMotions(targets.topology, energy.free, energy.held, dim)
        index = self.system.index[energy.needle_vertices]
        index = index[index >= 0]
        self._needle_coordinates = (index[:, None] * dim + np.arange(dim)).ravel()
        # The factor, its matrix and the projection off its rigid motions that the previous
        # keep_factor run ended with (see run(keep_factor=True)).
        self._kept: tuple[Any, sp.csr_array, RigidProjection] | None = None
        self._kept_damping = INITIAL_DAMPING
        self._double = False  # a single-precision factor was too inexact: double from now on
        self._paused: _Iteration | None = None  # a run stopped at its time limit (resume)
        self._iteration_seconds: dict[str, float | None] = {"refresh": None, "step": 0.0}
        """Seconds of the last iteration with a factorization and without (the time limit
        stops before an iteration that would end past it); None: no factorization timed or
        estimated yet (:meth:`expect_refresh`)."""

    def set_handle_targets(self, soft_positions: np.ndarray | None = None,
                           frame_edges: np.ndarray | None = None) -> None:
        """Replace the soft handle positions (p, dim) and the orientation handles' target
        edge vectors (q, 2, dim) (``None`` keeps the current ones)."""
        self.form_energy.set_handle_targets(soft_positions, frame_edges)

    def energy(self, vertices: np.ndarray) -> float:
        """E of (n, dim) positions (fixed vertices as given)."""
        return self.form_energy.energy(np.asarray(vertices, dtype=np.float64))

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
            frame_edges: np.ndarray | None = None, max_iterations: int = MAX_ITERATIONS,
            tolerance: float = TOLERANCE, time_limit: float | None = None,
            keep_factor: bool = False, progress: Any = None,
            start_energy: float | None = None, interactive: bool | None = None,
            ) -> Refinement:
        """Refine from ``start`` (n, dim); fixed vertices keep their ``start`` positions.

        ``soft_positions`` (p, dim) and ``frame_edges`` (q, 2, dim) replace the handle
        targets given at construction. ``keep_factor``: start from the factorization the
        previous ``keep_factor`` run ended with and keep this run's for the next (for a
        session's drags, which are alike); convergence may then be declared on a
        quasi-Newton step of that kept factor, without a fresh factorization to confirm it.
        A run that stops at ``time_limit`` can be continued by :meth:`resume`.
        ``start_energy``: :meth:`energy` of ``start`` with these handle targets, when the
        caller has it. ``interactive`` (default: ``keep_factor``): convergence may be
        declared on a step of a kept factor without the checks a one-shot refinement makes
        (a session's drags); ``keep_factor=True, interactive=False`` keeps factors from run
        to run but converges as a one-shot refinement does (the rows of a blend sequence,
        :func:`solver.blend`, whose answers are compared with independent ones). See
        :func:`refine` for the rest.
        """
        clock = time.perf_counter()
        self.set_handle_targets(soft_positions, frame_edges)
        with _BLAS.limit(limits=1, user_api="blas"):
            state = _Iteration.start(self, np.array(start, dtype=np.float64), keep_factor,
                                     max_iterations, tolerance, start_energy)
            state.interactive = keep_factor if interactive is None else interactive
            return self._advance(state, time_limit, progress, clock)

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

    def resume(self, time_limit: float | None = None, progress: Any = None) -> Refinement:
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
            return self._advance(state, time_limit, progress, clock)

    def _advance(self, state: _Iteration, time_limit: float | None, progress: Any,
                 clock: float) -> Refinement:
        """Iterate ``state`` until it stops (:meth:`_iterate`); the :class:`Refinement`."""
        self._paused = None
        self._iterate(state, time_limit, _iteration_notifier(progress, time_limit), clock)
        if state.stop == "time_limit":
            self._paused = state
        if state.keep_factor and state.factor is not None:
            self._kept = (state.factor, state.model, state.projection)
            self._kept_damping = state.damping
        return Refinement(vertices=state.X.copy(), report=with_outcome({
            "refined": True, **state.counters(), "after": self.residuals(state.X),
            "angle_weight": self.targets.angle_weight,
            "seconds": time.perf_counter() - clock}))

    def _iterate(self, s: _Iteration, time_limit: float | None, notify: Any,
                 clock: float) -> None:
        """The iteration of :meth:`run` and :meth:`resume`, advancing ``s`` in place until
        it converges, runs out of iterations or reaches ``time_limit`` (it stops before an
        iteration or a factorization that the last one of its kind says would end past it)."""
        system = self.system
        s.stop = "max_iterations"
        while s.iterations < s.max_iterations and system.n_free and not s.converged:
            refresh = s.factor is None or s.frozen_steps >= s.max_frozen
            if not self._fits(s, refresh, time_limit, clock):
                s.stop = "time_limit"
                break
            began, factorizations = time.perf_counter(), s.factorizations
            s.iterations += 1
            energy, H, g = system.normal_equations(s.X, matrix=refresh)
            s.memory.observe(g)
            if energy <= EXACT_ENERGY:
                s.stop, s.converged = "exact", True
                break
            accepted = False
            while not accepted and s.damping <= MAX_DAMPING:
                if refresh:
                    s.factor = None  # frees its analysis for the cache: the next one reuses it
                    try:
                        s.factor = self._damped_factor(H, s.damping, not s.keep_factor)
                    except SingularSystemError:
                        s.damping, s.rejected = s.damping * 10.0, s.rejected + 1
                        continue
                    s.factorizations += 1
                    s.precisions.add(s.factor.precision)
                    s.model, s.fresh, s.frozen_steps, s.factor_gain = H, True, 0, 0.0
                    s.projection = self.rigid_motions.at(s.X[self.form_energy.free])
                    s.memory.clear()
                s.solves += 1
                try:
                    step, slope, predicted = s.direction(g, system)
                except ImpreciseSolveError:
                    # A single-precision factor too inexact here (or a float32 answer that
                    # is not finite): this refiner factorizes in double from now on, here
                    # first, as after a refused step (its time limit included).
                    self._double = True
                    if self._refresh_stopped(s, time_limit, clock):
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
                        and gained < FROZEN_GAIN * predicted):
                    # A step of a factor built elsewhere that lowers E by less than half its
                    # prediction went astray: a fresh step from here does better (angles
                    # x 0.8: one taken with gain 0.14 left the next fresh step 2e-4 of E
                    # short, and the answer 10x further from the optimum).
                    found = None
                accepted = found is not None
                # The factor of a nearby point, whose last step it predicted well, expects
                # less than ENERGY_TOLERANCE of E from here (a Newton-decrement test): what
                # is left is below the convergence test, confirmed without a fresh
                # factorization (x 0.8 forms: one factorization fewer).
                moved = float(np.abs(step).max(initial=0.0)) / system.energy.scale
                # So does one whose step, refused, gained at most that much at its best
                # length while the factor predicted at most REFUSED_PREDICTION times it (not
                # in a session's drags, whose kept factors come from other shapes).
                negligible = (not s.fresh and _trusted(s)
                              and (s.interactive or moved <= QUASI_NEWTON_REACH)
                              and (predicted <= ENERGY_TOLERANCE * energy
                                   or (found is None and not s.interactive
                                       and gained <= ENERGY_TOLERANCE * energy
                                       and predicted <= REFUSED_PREDICTION
                                       * ENERGY_TOLERANCE * energy)))
                if found is None:
                    s.rejected += 1
                    if negligible:
                        s.stop, s.converged = "converged", True
                        break
                    if s.fresh:
                        s.damping = max(s.damping * s.growth, REFUSED_DAMPING)
                        s.growth *= 2.0
                    if self._refresh_stopped(s, time_limit, clock):
                        break
                    if not s.fresh and H is None:  # a kept factor failed: rebuild it here
                        energy, H, g = system.normal_equations(s.X)
                    refresh = True
                    continue
                alpha, trial, new_energy = found
                s.memory.moved(alpha * step, g, system, s.model)
                gain = (energy - new_energy) / predicted if predicted > 0 else 0.0
                # A full Gauss-Newton step (fresh matrix, little damping) that barely lowers
                # E: converged. A quasi-Newton, shortened or heavily damped step says nothing.
                full = s.fresh and alpha == 1.0 and s.damping <= 1.0
                decrease, s.X, s.energy = energy - new_energy, trial, new_energy
                energy = new_energy
                s.trace.append(energy)
                s.steps.append(moved)
                notify(s.iterations, s.factorizations, energy, time.perf_counter() - clock)
                # ... unless E still falls fast (Gauss-Newton's quadratic convergence where the
                # forms are met): then a few more steps are cheap and reach round-off.
                slowing = decrease <= 0.5 * (energy + decrease)
                small = moved <= s.tolerance or decrease <= ENERGY_TOLERANCE * energy
                if (full and small and slowing) or negligible or energy <= EXACT_ENERGY:
                    s.stop, s.converged = "converged", True
                elif small and slowing and not s.fresh:
                    # A small full step on a kept factor whose model just predicted the
                    # decrease well (gain near 1) is as good as a fresh one: that factor is
                    # the Gauss-Newton matrix of a nearby point. Interactive runs
                    # (keep_factor) accept it outright; others only where it also moved
                    # little (a small decrease of E on a flat valley floor can leave the
                    # answer 1e-3 of its size from the optimum). A well-predicted step that
                    # moved more takes the next step on the same factor (cactus x 0.8: 2
                    # factorizations instead of 3); any other is confirmed by a fresh one.
                    well = alpha == 1.0 and _trusted(s, gain)
                    if s.interactive or (well and moved <= QUASI_NEWTON_REACH):
                        s.stop, s.converged = "converged", True
                    elif not well or s.frozen_steps > SMALL_FROZEN_STEPS:
                        s.frozen_steps = s.max_frozen
                if s.fresh:  # Levenberg-Marquardt's damping update (Nielsen)
                    s.damping = max(MIN_DAMPING, s.damping * (
                        max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3) if alpha == 1.0
                        else 10.0))
                    s.growth = 2.0
                # The next steps reuse this factor (quasi-Newton, one back-substitution each)
                # while they lower E about as predicted; otherwise it is rebuilt at the new X.
                s.fresh, s.factor_gain = False, gain
                s.frozen_steps += 1
                # ... nor, unless it was kept, after a long step: a model built before a
                # move of more than FROZEN_REACH edge lengths was refused in every measured
                # case (x0.8 forms, strong deformations).
                if gain < s.min_gain or (moved > FROZEN_REACH and not s.kept):
                    s.frozen_steps = s.max_frozen
            if s.stop == "time_limit":
                break
            kind = "refresh" if s.factorizations > factorizations else "step"
            self._iteration_seconds[kind] = time.perf_counter() - began
            if not accepted and not s.converged:  # no step lowers E: stationary
                s.stop, s.converged = "stationary", True
            elif not s.converged and _stalled(s.trace):
                s.stop = "stalled"
                break
        if not system.n_free:
            s.stop, s.converged = "no_free_vertices", True

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

    def _fits(self, s: _Iteration, refresh: bool, time_limit: float | None,
              clock: float) -> bool:
        """Whether an iteration (a factorization first where ``refresh``) ends before
        ``time_limit`` seconds after ``clock``, judged by the last one of its kind (or by
        :meth:`expect_refresh`'s estimate; with neither it starts while time is left)."""
        if time_limit is None:
            return True
        left = time_limit - (time.perf_counter() - clock)
        kind = "refresh" if refresh or s.factor is None else "step"
        return left > (self._iteration_seconds[kind] or 0.0)

    def _refresh_stopped(self, s: _Iteration, time_limit: float | None,
                         clock: float) -> bool:
        """Whether the factorization that the iteration of ``s`` needs now would end past
        ``time_limit``: then the run stops here (``time_limit``), and a resumed run starts
        this iteration again with that factorization."""
        if self._fits(s, True, time_limit, clock):
            return False
        s.frozen_steps, s.stop = s.max_frozen, "time_limit"
        s.iterations -= 1
        return True

    def _damped_factor(self, H: sp.csr_array, damping: float, single: bool = False) -> Any:
        """Factorization of ``H + damping D`` (Levenberg-Marquardt with Marquardt's scaling:
        ``D`` is the diagonal of H floored at 1e-9 of its median, which is also added, so
        that H + D is definite). Raises :class:`SingularSystemError` where the backend
        finds it singular.

        At the vertices of needle edges (:attr:`FormEnergy.needle_vertices`) ``D`` is
        capped at the median diagonal. Their diagonal is that of the needle's relative
        length, ~1e8 times the others' on an edge 1e-4 of the mean long, and it is stiff
        along the needle only: scaled by it, even the first step's damping of 1e-9 held the
        vertices' other directions back as a damping of 0.1 would, and Gauss-Newton
        crawled (rocker-arm with 30 such edges, noisy angles: 10 iterations and 4
        factorizations, stopped 1% above the optimum's energy and 5.1e-5 of the diagonal
        from the original; 2 and 2 with the cap, at the optimum, 2.3e-5; the held-out
        mesh's size, stanford-bunny: 11 and 8, 1.4e-4; 2 and 2, 3.3e-5). The floor was
        1e-9 of the *mean* diagonal, which those edges dominate: it damped every other
        vertex by ~1e-4 of its diagonal. Flattened faces keep the full scaling: their
        vertices' large diagonal is their angles', and a step that turns them over is what
        the damping must hold back (capping it there too stalled rocker-arm's capped faces).

        PARDISO orders this matrix itself (no ``groups`` hint): that keeps its two-level
        factor, which a given ordering turns into the classic one. On the Gauss-Newton
        matrix its factorizations are 1.1-1.3x and its solves 1.7x faster than with the
        hint, its analysis (once per pattern, then cached) 1.2x slower (rocker-arm and
        beetle, two MKL threads: ``python -m bench.gauss_newton_factor``). It factorizes
        in single precision where ``single`` asks for it and the diagonal allows
        (:func:`factor_precision`), and in double from the first time single precision
        finds the matrix not positive definite or one of its solves too inexact
        (:meth:`_iterate`). Interactive runs (``keep_factor``) factorize in double: their
        factors serve many solves, each of which single precision makes three times as
        costly (two back-substitutions and a product), and a session's pattern is analysed
        ahead of time in one precision (:meth:`prepare`)."""
        positions = self.system.diagonal_positions
        diag = H.data[positions]
        median = float(np.median(diag))
        floor = 1e-9 * median
        scale = np.maximum(diag, floor)
        needle = self._needle_coordinates
        scale[needle] = np.minimum(scale[needle], median)
        values = H.data.copy()
        values[positions] += damping * scale + floor
        damped = sp.csr_array((values, H.indices, H.indptr), shape=H.shape)
        damped.has_canonical_format = True
        if (single and not self._double and resolve_backend(self.backend) == "pardiso"
                and factor_precision(values[positions]) == "single"):
            try:
                return SinglePrecisionFactor(damped, self.backend, SINGLE_PRECISION_ERROR)
            except SingularSystemError:
                self._double = True
        return factorize(damped, self.backend, triangle="upper")

    def _line_search(self, X: np.ndarray, step: np.ndarray, energy: float, slope: float,
                     ) -> tuple[float, np.ndarray, float] | None:
        """Backtracking along ``step`` (n_free * dim,) from ``X`` (n, dim) at energy
        ``energy`` with directional derivative ``slope`` < 0: the first of
        :data:`STEP_FRACTIONS` that decreases E sufficiently (Armijo), as ``(fraction, new
        positions, new E)``, or None. It costs energies, never factorizations."""
        free, dim = self.form_energy.free, self.form_energy.dim
        for alpha in STEP_FRACTIONS:
            trial = X.copy()
            trial[free] += alpha * step.reshape(-1, dim)
            new_energy = self.form_energy.energy(trial)
            if np.isfinite(new_energy) and new_energy < energy + ARMIJO * alpha * slope:
                return alpha, trial, new_energy
        return None


@dataclass
class _Iteration:
    """Everything :meth:`Refiner._iterate` carries from step to step, so that a run stopped
    at its time limit resumes exactly where it stopped (:meth:`Refiner.resume`)."""

    X: np.ndarray
    before: dict[str, Any]
    energy0: float
    energy: float
    keep_factor: bool
    interactive: bool  # loose convergence on kept factors (Refiner.run's ``interactive``)
    kept: bool
    max_frozen: int
    min_gain: float
    memory: QuasiNewtonMemory
    max_iterations: int
    tolerance: float
    factor: Any = None
    model: sp.csr_array | None = None
    projection: RigidProjection | None = None  # off the rigid motions where factor was built
    damping: float = INITIAL_DAMPING
    growth: float = 2.0
    fresh: bool = False  # whether ``factor`` was computed at the current X
    factor_gain: float = 0.0  # gain ratio of the last step taken with ``factor``
    frozen_steps: int = 0
    iterations: int = 0
    rejected: int = 0
    factorizations: int = 0
    precisions: set[str] = field(default_factory=set)  # of the factorizations
    solves: int = 0
    slices: int = 1
    stop: str = "max_iterations"
    converged: bool = False
    trace: list[float] = field(default_factory=list)
    steps: list[float] = field(default_factory=list)

    @classmethod
    def start(cls, refiner: Refiner, X: np.ndarray, keep_factor: bool, max_iterations: int,
              tolerance: float, energy: float | None = None) -> _Iteration:
        """The state before the first step from ``X`` (n, dim). With ``keep_factor`` the
        previous run's factor (and damping) is the first model: consecutive drags of a
        session are alike; a run that starts from a lightly damped kept factor keeps its
        factors longer (see :data:`KEPT_STEPS`)."""
        energy = refiner.form_energy.energy(X) if energy is None else energy
        factor, model, projection = (refiner._kept if keep_factor and refiner._kept
                                     else (None, None, None))
        damping = refiner._kept_damping if factor is not None else INITIAL_DAMPING
        kept = factor is not None and damping <= KEPT_DAMPING
        max_frozen, min_gain = (KEPT_STEPS, KEPT_GAIN) if kept else (MAX_FROZEN_STEPS,
                                                                     FROZEN_GAIN)
        return cls(X=X, before=refiner.residuals(X), energy0=energy, energy=energy,
                   keep_factor=keep_factor, interactive=keep_factor, kept=kept,
                   max_frozen=max_frozen,
                   min_gain=min_gain,
                   memory=QuasiNewtonMemory(QUASI_NEWTON_MEMORY if kept else 0),
                   max_iterations=max_iterations, tolerance=tolerance, factor=factor,
                   model=model, projection=projection, damping=damping,
                   factor_gain=1.0 if factor is not None else 0.0, trace=[energy])

    def direction(self, g: np.ndarray, system: GaussNewtonSystem,
                  ) -> tuple[np.ndarray, float, float]:
        """The step from here for the gradient ``g`` (n_free * dim,), its slope ``g.step``
        and the decrease of E its model predicts: the Gauss-Newton step on a fresh factor,
        else the L-BFGS step with the factor as initial Hessian (whose model along the
        step predicts ``-slope / 2``). Raises :class:`ImpreciseSolveError` (from
        :meth:`solve`)."""
        if self.fresh:
            step = -self.solve(g)
            slope = float(np.einsum("i,i->", g, step))  # < 0: H + D is SPD
            # Gain ratio of the full step: actual decrease over the model's.
            return step, slope, -slope - 0.5 * system.quadratic_form(self.model, step)
        step = -self.memory.inverse_hessian(self.solve, g)
        slope = float(np.einsum("i,i->", g, step))
        return step, slope, -0.5 * slope

    def solve(self, v: np.ndarray) -> np.ndarray:
        """``factor^-1 v`` (n_free * dim,) without its rigid motions
        (:mod:`solver.rigid_motions`: a factor used away from where it was built would
        otherwise turn the damping's inverse into a huge linearized rotation).

        A single-precision factor (:class:`~solver.mixed_precision.SinglePrecisionFactor`)
        refines its answer by one more back-substitution, counted in ``solves``, and
        raises :class:`~solver.mixed_precision.ImpreciseSolveError` where that corrects
        it by more than :data:`SINGLE_PRECISION_ERROR`."""
        if isinstance(self.factor, SinglePrecisionFactor):
            self.solves += 1  # its refinement step's back-substitution
            return self.factor.solve(v, self.projection)
        x = self.factor.solve(v)
        return x if self.projection is None else self.projection(x)

    def counters(self) -> dict[str, Any]:
        """The report's fields of the refinement so far."""
        return {"converged": self.converged, "stop_reason": self.stop,
                "iterations": self.iterations, "rejected_steps": self.rejected,
                "factorizations": self.factorizations,
                "precision": ("mixed" if len(self.precisions) > 1
                              else next(iter(self.precisions), "double")),
                "solves": self.solves,
                "slices": self.slices, "energy_before": self.energy0,
                "energy_after": self.energy, "energy_trace": list(self.trace),
                "step_trace": list(self.steps), "before": self.before}


def factor_precision(diagonal: np.ndarray) -> str:
    """The precision to factorize a damped Gauss-Newton matrix in, from its diagonal.

    Single precision nearly halves the factorization's time (:mod:`solver.mixed_precision`),
    and with one refinement step per solve the steps are those of double precision (x 0.8
    and noisy forms take the same steps to the same energies). Needle edges and flattened
    faces make entries of the diagonal 1e8 times the others (the stiffness of a residual
    grows as the inverse square of the edge's length or the face's width), beyond what
    float32 resolves: a refinement factorized in single precision there converged to a 25%
    higher energy. The diagonal's spread separates the two: 12-200 on every bench mesh,
    1.5e8 and more with needle edges (:data:`SINGLE_PRECISION_SPREAD`). Soft modes that
    the diagonal does not show are caught by the solves themselves
    (:data:`SINGLE_PRECISION_ERROR`).

    Args:
        diagonal: (N,) float64 diagonal of the damped matrix (positive).

    Returns:
        ``"single"`` or ``"double"``.
    """
    if not len(diagonal):
        return "double"
    spread = float(diagonal.max()) / float(np.median(diagonal))
    return "single" if spread <= SINGLE_PRECISION_SPREAD else "double"


def _stalled(trace: list[float]) -> bool:
    """Whether the last :data:`STALL_STEPS` steps together lowered E by at most
    :data:`ENERGY_TOLERANCE` of it: less than one step of a converging run may, and the
    damping has grown past where a step counts as a Gauss-Newton step."""
    return (len(trace) > STALL_STEPS
            and trace[-1 - STALL_STEPS] - trace[-1] <= ENERGY_TOLERANCE * trace[-1])


def _trusted(s: _Iteration, gain: float | None = None) -> bool:
    """Whether the factor of ``s`` is a good model here: lightly damped, and its last step
    (or the step just taken, whose gain ratio is ``gain``) lowered E about as it predicted
    (gain ratio within 0.25 of 1)."""
    gain = s.factor_gain if gain is None else gain
    return s.damping <= 1.0 and abs(gain - 1.0) <= 0.25


_BLAS = ThreadpoolController()
"""The refinement's vectors are too short for a multithreaded BLAS to pay: on a loaded
machine its threads cost ~20 ms per dot product (docs/refinement.md), so :meth:`Refiner.run`
limits BLAS to one thread while it iterates."""


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
        time_limit: optional wall-clock budget in seconds: the refinement stops before an
            iteration (or a factorization) that, timed like the last one of its kind by
            this :class:`Refiner`, would end past it (the first factorization of a run
            that has none starts while time is left). It returns the best iterate,
            ``converged`` False and ``stop_reason`` ``"time_limit"``.
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
