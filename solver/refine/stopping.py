"""When the refinement stops: its stop reasons, its stopping rules as data, one predicate each.

:class:`StopReason` lists why a refinement ended (a report's ``stop_reason``), with the
words its outcome uses and what each means; :class:`StopRules` holds the thresholds; the
functions below are the rules themselves. :meth:`solver.refine.Refiner.run` asks them and
decides nothing else about stopping. Why each threshold has its value (measurements):
``docs/refinement.md``, "Stopping rules".

Example:
    >>> rules = StopRules(stall_steps=2)
    >>> stalled(rules, [10.0, 9.9999, 9.9998]), stalled(rules, [10.0, 5.0, 2.0])
    (True, False)
    >>> StopReason("stalled").converged, StopReason.EXACT.converged
    (False, True)
    >>> settled(rules, [10.0, 9.9999, 9.9998], [1e-6, 2e-6]), settled(
    ...     rules, [10.0, 9.9999, 9.9998], [1e-6, 0.3])  # the same stall, a step that moved
    (True, False)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal


@dataclass(frozen=True)
class StopRules:
    """The thresholds of the refinement's stopping rules (:mod:`solver.stopping`)."""

    max_iterations: int = 50
    """Iterations (each at most one Gauss-Newton matrix and its factorizations) after which a
    run stops unconverged."""
    tolerance: float = 1e-4
    """A full Gauss-Newton step that moved no vertex by more than this fraction of the mean
    target edge length is small (:func:`small_step`)."""
    energy_tolerance: float = 1e-3
    """... as is one that lowered E by at most this fraction of E."""
    stall_steps: int = 5
    """A run whose last this many steps together lowered E by at most ``energy_tolerance`` of
    it stops as stalled (:func:`stalled`)."""
    exact_energy: float = 1e-24
    """E at or below this: the forms are met to round-off."""
    max_damping: float = 1e12
    """Relative damping past which no step is possible (stationary)."""
    light_damping: float = 1.0
    """Largest relative damping at which a step counts as a Gauss-Newton step, and a factor's
    model is trusted (:func:`trusted`)."""
    trusted_gain: float = 0.25
    """A factor is trusted where its last step's gain ratio (actual over predicted decrease) is
    within this of 1."""
    slowing: float = 0.5
    """A step is slowing where it lowered E by at most this fraction of E before it (quadratic
    convergence near round-off is not slowing)."""
    quasi_newton_reach: float = 1e-2
    """A run that is not interactive ends on a step of a factor built elsewhere only if that
    step moved no vertex by more than this fraction of the mean target edge length."""
    refused_prediction: float = 2.0
    """A refused step of a trusted factor that gained at most ``energy_tolerance`` of E ends a
    run that is not interactive where the factor predicted at most this many times
    ``energy_tolerance`` of E."""
    small_frozen_steps: int = 2
    """Further steps a factor may take after a small, well-predicted step of its own that moved
    more than ``quasi_newton_reach`` before a fresh factorization must confirm convergence
    (fewer than ``stall_steps``)."""


DEFAULT_STOP_RULES = StopRules()
"""The rules every refinement uses unless given others."""


class StopReason(StrEnum):
    """Why a refinement stopped (a refinement report's ``stop_reason``)."""

    CONVERGED = "converged"
    EXACT = "exact"
    STATIONARY = "stationary"
    NO_FREE_VERTICES = "no_free_vertices"
    STALLED = "stalled"
    MAX_ITERATIONS = "max_iterations"
    TIME_LIMIT = "time_limit"

    @property
    def converged(self) -> bool:
        """Whether a run that stops for this reason has converged."""
        return self in _CONVERGED

    @property
    def words(self) -> str:
        """The reason in the words of a report's ``outcome_text``."""
        return _WORDS[self]

    @property
    def meaning(self) -> str:
        """When a refinement stops for this reason (the default rules' values)."""
        return _MEANINGS[self]


_CONVERGED = frozenset({StopReason.CONVERGED, StopReason.EXACT, StopReason.STATIONARY,
                        StopReason.NO_FREE_VERTICES})
_WORDS = {StopReason.TIME_LIMIT: "time limit", StopReason.MAX_ITERATIONS: "iteration budget",
          StopReason.STALLED: "stalled (no further progress)",
          StopReason.STATIONARY: "stationary", StopReason.CONVERGED: "converged",
          StopReason.EXACT: "exact", StopReason.NO_FREE_VERTICES: "no free vertices"}
_R = DEFAULT_STOP_RULES
_MEANINGS = {
    StopReason.CONVERGED: "a small full Gauss-Newton step (no vertex moved by more than "
                          f"{_R.tolerance:g} of the mean edge length, or E lowered by less "
                          f"than {_R.energy_tolerance:.1%}), or a trusted factor expects less "
                          f"than that from here, or the last {_R.stall_steps} steps each moved "
                          f"less than {_R.tolerance:g} and together lowered E by less than "
                          f"{_R.energy_tolerance:.1%}",
    StopReason.EXACT: f"E at most {_R.exact_energy:g}: the forms are met to round-off",
    StopReason.STATIONARY: "no step lowers E, however damped",
    StopReason.NO_FREE_VERTICES: "every vertex is held",
    StopReason.STALLED: f"the last {_R.stall_steps} steps together lowered E by less than "
                        f"{_R.energy_tolerance:.1%}",
    StopReason.MAX_ITERATIONS: f"the iteration budget ({_R.max_iterations}) ran out",
    StopReason.TIME_LIMIT: "the time budget ran out (the answer is the best shape so far)",
}


def describe_stop_reasons() -> str:
    """Every stop reason with its meaning, in one sentence (the HTTP schema's and docs'
    description of ``stop_reason``)."""
    return "; ".join(f"{reason.value}: {reason.meaning}" for reason in StopReason) + "."


CONFIRM = "confirm"
"""A step that would converge if a fresh factorization confirmed it (:func:`after_step`)."""


def out_of_budget(rules: StopRules, iterations: int, n_free: int) -> StopReason | None:
    """Why a run stops before its next iteration, if it does: no free vertex, or
    ``iterations`` have reached ``rules.max_iterations``."""
    if not n_free:
        return StopReason.NO_FREE_VERTICES
    if iterations >= rules.max_iterations:
        return StopReason.MAX_ITERATIONS
    return None


def exact(rules: StopRules, energy: float) -> bool:
    """Whether E is round-off: the forms are met."""
    return energy <= rules.exact_energy


def stationary(rules: StopRules, damping: float) -> bool:
    """Whether the relative ``damping`` is past where a step is possible."""
    return damping > rules.max_damping


def trusted(rules: StopRules, damping: float, gain: float) -> bool:
    """Whether a factor is a good model here: lightly damped, and its last step (gain ratio
    ``gain``) lowered E about as it predicted."""
    return damping <= rules.light_damping and abs(gain - 1.0) <= rules.trusted_gain


def negligible(rules: StopRules, *, fresh: bool, trusted: bool, interactive: bool,
               moved: float, predicted: float, energy: float, refused: bool,
               gained: float) -> bool:
    """Whether a factor built elsewhere (not ``fresh``) and ``trusted`` expects nothing
    worth a step from here (a Newton-decrement test): it predicts at most
    ``energy_tolerance`` of ``energy`` (E before the step), or its step, ``refused``,
    ``gained`` at most that at its best length while it predicted at most
    ``refused_prediction`` times it (not in ``interactive`` runs, whose kept factors come
    from other shapes). Outside interactive runs the step must also have ``moved`` (in
    mean edge lengths) at most ``quasi_newton_reach``."""
    if fresh or not trusted or not (interactive or moved <= rules.quasi_newton_reach):
        return False
    least = rules.energy_tolerance * energy
    return predicted <= least or (refused and not interactive and gained <= least
                                  and predicted <= rules.refused_prediction * least)


def small_step(rules: StopRules, moved: float, decrease: float, energy: float) -> bool:
    """Whether a step that ``moved`` no vertex by more than that (in mean edge lengths) and
    lowered E by ``decrease`` to ``energy`` was small."""
    return moved <= rules.tolerance or decrease <= rules.energy_tolerance * energy


def slowing(rules: StopRules, decrease: float, energy: float) -> bool:
    """Whether a step that lowered E by ``decrease`` to ``energy`` is not in the fast
    (quadratic) descent of Gauss-Newton where the forms are met."""
    return decrease <= rules.slowing * (energy + decrease)


def after_step(rules: StopRules, *, fresh: bool, interactive: bool, alpha: float,
               damping: float, gain: float, moved: float, decrease: float, energy: float,
               negligible: bool, frozen_steps: int, exact_solve: bool = True,
               ) -> StopReason | Literal["confirm"] | None:
    """What an accepted step means for stopping: :attr:`StopReason.CONVERGED`,
    :data:`CONFIRM` (a fresh factorization must confirm it) or None (go on).

    A full Gauss-Newton step (``fresh`` factor, ``alpha`` 1, lightly damped) that is small
    and slowing converges, as does a ``negligible`` one or one that reached round-off. A
    small, slowing step of a factor built elsewhere converges in ``interactive`` runs; in
    others where it was well predicted (``alpha`` 1, ``gain`` trusted) and moved at most
    ``quasi_newton_reach``; a well-predicted one that moved more takes up to
    ``small_frozen_steps`` more steps on that factor; any other is confirmed. A fresh step
    whose linear solve was inexact (not ``exact_solve``: CG stopped at a loose forcing term,
    :mod:`solver.refine.iterative_steps`) is short of the Gauss-Newton step by an unknown
    amount, so it proves nothing: a small one is confirmed by a tightly solved step."""
    if fresh and not exact_solve:
        small = small_step(rules, moved, decrease, energy)
        if small and slowing(rules, decrease, energy) and not exact(rules, energy):
            return CONFIRM
    full = fresh and alpha == 1.0 and damping <= rules.light_damping and exact_solve
    small = small_step(rules, moved, decrease, energy)
    slow = slowing(rules, decrease, energy)
    if (full and small and slow) or negligible or exact(rules, energy):
        return StopReason.CONVERGED
    if small and slow and not fresh:
        well = alpha == 1.0 and trusted(rules, damping, gain)
        if interactive or (well and moved <= rules.quasi_newton_reach):
            return StopReason.CONVERGED
        if not well or frozen_steps > rules.small_frozen_steps:
            return CONFIRM
    return None


def stalled(rules: StopRules, trace: Sequence[float]) -> bool:
    """Whether the last ``stall_steps`` steps of ``trace`` (E after each step, the start
    first) together lowered E by at most ``energy_tolerance`` of it."""
    steps = rules.stall_steps
    return len(trace) > steps and trace[-1 - steps] - trace[-1] <= (
        rules.energy_tolerance * trace[-1])


def settled(rules: StopRules, trace: Sequence[float], moves: Sequence[float]) -> bool:
    """Whether a run :func:`stalled` where it stands: its last ``stall_steps`` steps each
    proposed moving no vertex by more than ``tolerance`` of the mean edge length (``moves``,
    one per accepted step, in mean edge lengths) and together lowered E by at most
    ``energy_tolerance`` of it -- the small-step test of :func:`after_step`, held over
    ``stall_steps`` steps instead of one full Gauss-Newton step (which damping may never
    allow where E is flat to round-off, e.g. thousands of separate parts)."""
    steps = rules.stall_steps
    return (stalled(rules, trace) and len(moves) >= steps
            and max(moves[-steps:]) <= rules.tolerance)


def after_iteration(rules: StopRules, accepted: bool, trace: Sequence[float],
                    moves: Sequence[float] = ()) -> StopReason | None:
    """Why a run that has not converged stops after an iteration, if it does: no step was
    accepted however damped (stationary), it :func:`settled` (converged), or it
    :func:`stalled`."""
    if not accepted:
        return StopReason.STATIONARY
    if settled(rules, trace, moves):
        return StopReason.CONVERGED
    if stalled(rules, trace):
        return StopReason.STALLED
    return None
