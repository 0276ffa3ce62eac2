"""The refinement's stall rules (solver.refine.stopping): a run whose last steps neither move
nor lower E is settled (converged); one that still moves while E stays is stalled."""

from __future__ import annotations

import pytest

from solver.refine.stopping import (
    DEFAULT_STOP_RULES,
    StopReason,
    after_iteration,
    settled,
    stalled,
)

RULES = DEFAULT_STOP_RULES
FLAT = [1.0, *(1.0 - 1e-9 * k for k in range(1, RULES.stall_steps + 1))]
"""E after each of ``stall_steps`` steps that lowered it by round-off only."""


@pytest.mark.parametrize("moves,reason", [
    ([1e-7] * RULES.stall_steps, StopReason.CONVERGED),           # flat and still: settled
    ([1e-7] * (RULES.stall_steps - 1) + [10 * RULES.tolerance], StopReason.STALLED),
    ([0.3] * RULES.stall_steps, StopReason.STALLED),               # flat, moving: stalled
])
def test_a_stall_is_settled_only_where_the_steps_stopped_moving(moves, reason):
    assert stalled(RULES, FLAT)
    assert after_iteration(RULES, True, FLAT, moves) == reason
    assert settled(RULES, FLAT, moves) == (reason == StopReason.CONVERGED)


def test_steps_that_still_lower_e_are_neither():
    falling = [1.0 / 2 ** k for k in range(RULES.stall_steps + 1)]
    still = [1e-7] * RULES.stall_steps
    assert not stalled(RULES, falling) and not settled(RULES, falling, still)
    assert after_iteration(RULES, True, falling, still) is None


def test_too_few_steps_are_not_settled():
    few = [1e-7] * (RULES.stall_steps - 1)
    assert not settled(RULES, FLAT, few)
    assert after_iteration(RULES, True, FLAT, few) == StopReason.STALLED
    assert after_iteration(RULES, False, FLAT, few) == StopReason.STATIONARY


def test_the_converged_meaning_names_the_settled_rule():
    assert f"the last {RULES.stall_steps} steps each moved" in StopReason.CONVERGED.meaning
