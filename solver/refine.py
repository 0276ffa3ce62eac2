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
from dataclasses import dataclass
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
from .linalg import SingularSystemError, factorize
from .normal_equations import (  # noqa: F401 - re-exported
    PATTERN_CACHE_BYTES,
    GaussNewtonSystem,
    clear_pattern_cache,
    pattern_cache_info,
)

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
STEP_FRACTIONS = (1.0, 0.5, 0.25, 0.1)  # of a Gauss-Newton step tried before more damping
ARMIJO = 1e-4  # sufficient decrease: E(x + a d) < E(x) + ARMIJO a g.d
MAX_FROZEN_STEPS = 6  # steps on one factorization before it is rebuilt at the current X
FROZEN_GAIN = 0.5  # rebuild earlier when a step lowers E by less than this x its prediction
FROZEN_REACH = 0.5  # ... or moved a vertex by more than this many mean edge lengths
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
        self._kept: tuple[Any, sp.csr_array] | None = None  # see run(keep_factor=True)
        self._kept_damping = INITIAL_DAMPING

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
        session's drags, which are alike); convergence may then be declared on a
        quasi-Newton step of that kept factor, without a fresh factorization to confirm it.
        See :func:`refine` for the rest.
        """
        clock = time.perf_counter()
        with _BLAS.limit(limits=1, user_api="blas"):
            X, state = self._iterate(np.array(start, dtype=np.float64), soft_positions,
                                     frame_edges, max_iterations, tolerance, time_limit,
                                     keep_factor, _iteration_notifier(progress, time_limit),
                                     clock)
        return Refinement(vertices=X, report={
            "refined": True, **state, "after": self.residuals(X),
            "angle_weight": self.targets.angle_weight,
            "seconds": time.perf_counter() - clock})

    def _iterate(self, X: np.ndarray, soft_positions: np.ndarray | None,
                 frame_edges: np.ndarray | None, max_iterations: int, tolerance: float,
                 time_limit: float | None, keep_factor: bool, notify: Any, clock: float,
                 ) -> tuple[np.ndarray, dict[str, Any]]:
        """The iteration of :meth:`run`: (positions, the report's counters)."""
        system, energy_of = self.system, self.form_energy.energy
        self.set_handle_targets(soft_positions, frame_edges)
        before = self.residuals(X)
        energy0 = energy = energy_of(X)
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
        # A run that starts from the previous run's lightly damped factor (a session's next
        # drag) keeps its factors longer; see KEPT_STEPS.
        kept = factor is not None and damping <= KEPT_DAMPING
        max_frozen, min_gain = (KEPT_STEPS, KEPT_GAIN) if kept else (MAX_FROZEN_STEPS,
                                                                     FROZEN_GAIN)
        memory = _QuasiNewtonMemory(QUASI_NEWTON_MEMORY if kept else 0)
        while iterations < max_iterations and system.n_free and not converged:
            if time_limit is not None and time.perf_counter() - clock > time_limit:
                stop = "time_limit"
                break
            iterations += 1
            refresh = factor is None or frozen_steps >= max_frozen
            energy, H, g = system.normal_equations(X, matrix=refresh)
            memory.observe(g)
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
                    memory.clear()
                solves += 1
                if fresh:
                    step = -factor.solve(g)
                    slope = float(np.einsum("i,i->", g, step))  # < 0: H + D is SPD
                    # Gain ratio of the full step: actual decrease over the model's.
                    predicted = -slope - 0.5 * system.quadratic_form(model, step)
                else:  # L-BFGS on the factor: its model along the step is -slope / 2
                    step = -memory.inverse_hessian(factor, g)
                    slope = float(np.einsum("i,i->", g, step))
                    predicted = -0.5 * slope
                found = self._line_search(X, step, energy, slope) if slope < 0 else None
                accepted = found is not None
                if found is None:
                    rejected += 1
                    if fresh:
                        damping = max(damping * growth, REFUSED_DAMPING)
                        growth *= 2.0
                    elif H is None:  # a kept factor failed: rebuild it here
                        energy, H, g = system.normal_equations(X)
                    refresh = True
                    continue
                alpha, trial, new_energy = found
                memory.moved(alpha * step, g)
                gain = (energy - new_energy) / predicted if predicted > 0 else 0.0
                # A full Gauss-Newton step (fresh matrix, little damping) that barely lowers
                # E: converged. A quasi-Newton, shortened or heavily damped step says nothing.
                full = fresh and alpha == 1.0 and damping <= 1.0
                moved = float(np.abs(step).max(initial=0.0)) / system.energy.scale
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
                    frozen_steps = max_frozen
                if fresh:  # Levenberg-Marquardt's damping update (Nielsen)
                    damping = max(MIN_DAMPING, damping * (
                        max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3) if alpha == 1.0 else 10.0))
                    growth = 2.0
                # The next steps reuse this factor (quasi-Newton, one back-substitution each)
                # while they lower E about as predicted; otherwise it is rebuilt at the new X.
                fresh, factor_gain = False, gain
                frozen_steps += 1
                # ... nor, unless it was kept, after a long step: a model built before a
                # move of more than FROZEN_REACH edge lengths was refused in every measured
                # case (x0.8 forms, strong deformations).
                if gain < min_gain or (moved > FROZEN_REACH and not kept):
                    frozen_steps = max_frozen
            if not accepted:  # no step lowers E: a stationary point to working precision
                stop, converged = "stationary", True
        if not system.n_free:
            stop, converged = "no_free_vertices", True
        if keep_factor and factor is not None:
            self._kept, self._kept_damping = (factor, model), damping
        return X, {"converged": converged, "stop_reason": stop, "iterations": iterations,
                   "rejected_steps": rejected, "factorizations": factorizations,
                   "solves": solves, "energy_before": energy0, "energy_after": energy,
                   "energy_trace": trace, "step_trace": steps, "before": before}

    def _damped_factor(self, H: sp.csr_array, damping: float) -> Any:
        """Factorization of ``H + damping diag(H)`` (Levenberg-Marquardt; the diagonal is
        floored at 1e-9 of its mean, which is also added, so that H + D is definite).
        Raises :class:`SingularSystemError` where the backend finds it singular."""
        positions = self.system.diagonal_positions
        diag = H.data[positions]
        floor = 1e-9 * float(diag.mean())
        values = H.data.copy()
        values[positions] += damping * np.maximum(diag, floor) + floor
        damped = sp.csr_array((values, H.indices, H.indptr), shape=H.shape)
        damped.has_canonical_format = True
        return factorize(damped, self.backend, triangle="upper",
                         groups=self.system.ordering_groups)

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


class _QuasiNewtonMemory:
    """The last ``size`` steps ``s`` and gradient changes ``y`` since the factor was built,
    for L-BFGS's two-loop recursion (Nocedal and Wright, Alg. 7.4); with ``size`` 0 the
    steps are plain back-substitutions with the factor (frozen Gauss-Newton steps)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.pairs: list[tuple[np.ndarray, np.ndarray, float]] = []
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    def clear(self) -> None:
        self.pairs.clear()

    def moved(self, step: np.ndarray, gradient: np.ndarray) -> None:
        """A step ``step`` was taken from where the gradient was ``gradient``."""
        self._last = (step, gradient)

    def observe(self, gradient: np.ndarray) -> None:
        """The gradient after the last step: keep the pair where it has positive curvature."""
        if self._last is None or not self.size:
            return
        s, before = self._last
        self._last = None
        y = gradient - before
        sy = float(np.einsum("i,i->", s, y))
        if sy > 1e-12 * float(np.sqrt(np.einsum("i,i->", y, y) * np.einsum("i,i->", s, s))):
            self.pairs.append((s, y, 1.0 / sy))
            del self.pairs[:len(self.pairs) - self.size]

    def inverse_hessian(self, factor: Any, g: np.ndarray) -> np.ndarray:
        """``H^-1 g`` of L-BFGS with ``factor.solve`` as ``H_0^-1``."""
        q = g.copy()
        alphas = []
        for s, y, rho in reversed(self.pairs):
            a = rho * float(np.einsum("i,i->", s, q))
            alphas.append(a)
            q -= a * y
        r = factor.solve(q)
        for (s, y, rho), a in zip(self.pairs, reversed(alphas), strict=True):
            r += (a - rho * float(np.einsum("i,i->", y, r))) * s
        return r


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
