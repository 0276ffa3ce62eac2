"""The one progress rule of every backend (:class:`service.worker.runtime.ProgressThrottle`,
applied by :func:`service.operations.run`): at most one report per PROGRESS_INTERVAL, the
first and the last always, a stage change at once, a refinement iteration never lost."""

from __future__ import annotations

from typing import Any

from service import operations
from service.worker.runtime import PROGRESS_INTERVAL, ProgressThrottle
from tests.helpers.service import debug_task


def _throttle() -> tuple[ProgressThrottle, list[tuple[Any, ...]], list[float]]:
    sent: list[tuple[Any, ...]] = []
    now = [0.0]
    return ProgressThrottle(lambda *report: sent.append(report), clock=lambda: now[0]), sent, now


def test_reports_within_the_interval_are_held_and_the_newest_goes_next():
    throttle, sent, now = _throttle()
    throttle("charts", 0.0)
    for k in range(1, 100):
        now[0] = k * PROGRESS_INTERVAL / 40  # 40 reports per interval
        throttle("charts", k / 100)
    assert [f for _, f, _ in sent] == [0.0, 0.4, 0.8]  # one per interval, as it passes
    throttle.flush()
    assert sent[-1] == ("charts", 0.99, None)  # the last report, held back, goes at the end
    throttle.flush()
    assert len(sent) == 4  # nothing held: nothing more


def test_a_new_stage_goes_at_once_and_a_held_iteration_goes_with_the_next_report():
    throttle, sent, now = _throttle()
    throttle("factorize", 0.0)
    throttle("refine", 0.0)  # same instant, another stage
    assert [s for s, _, _ in sent] == ["factorize", "refine"]
    now[0] = 0.01
    throttle("refine", 0.1, {"iteration": 1, "energy": 2.0})
    throttle("refine", 0.2, {"iteration": 2, "energy": 1.0})
    throttle("refine", 0.3)
    assert len(sent) == 2  # all three held
    now[0] = 0.02
    throttle("encode", 0.0)
    assert sent[-1] == ("encode", 0.0, {"iteration": 2, "energy": 1.0})  # the newest step


def test_every_backend_gets_its_reports_through_the_throttle():
    """``operations.run`` is every worker's entry (local pool, Dask): a task's thousand
    reports reach the backend's callback throttled, ending at 1, with the task's timings."""
    sent: list[tuple[Any, ...]] = []
    result = operations.run(debug_task("debug.sleep", seconds=0.3, steps=1000),
                            lambda *report: sent.append(report))
    assert result.body == b'{"slept": true}' and "solve" in result.timings
    assert sent[0][:2] == ("solve", 0.0) and sent[-1][:2] == ("solve", 1.0)
    assert len(sent) <= 0.3 / PROGRESS_INTERVAL + 4, len(sent)
