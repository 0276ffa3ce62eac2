"""The outcome of a refinement, in one word and in words: converged, partly (stopped after
k iterations, and why) or not refined.

A refinement report's ``refined`` says whether the refinement ran; ``outcome`` says what it
achieved: ``"converged"`` (it reached the nearest surface, or the answer was exact),
``"partial"`` (it lowered the energy, then stopped unconverged: the time limit, the
iteration budget or a stall, after ``iterations`` iterations) or ``"not-refined"`` (it did
not run, or stopped before any step lowered the energy: the answer is its start).
``outcome_text`` says it in a sentence fragment ("partly: time limit after 2 iterations").
A refinement that stalled with its answer's quality targets met (a flattening without
warnings: :func:`stalled_at_targets`) says it is done ("done: quality targets met, stalled
(no further progress) after 16 iterations"); its ``outcome`` stays ``"partial"`` and its
``converged`` false, with ``targets_met`` true.

Example:
    >>> with_outcome({"refined": True, "converged": False, "stop_reason": "time_limit",
    ...               "iterations": 0, "energy_before": 80.27, "energy_after": 80.27})[
    ...     "outcome_text"]
    'not refined: time limit before the first iteration'
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .stopping import StopReason

OUTCOMES = ("converged", "partial", "not-refined")
"""The values of a refinement report's ``outcome``."""

STOP_WORDS = {reason.value: reason.words for reason in StopReason}
"""``stop_reason`` -> the words the outcome uses (:attr:`StopReason.words`)."""


def refinement_outcome(report: Mapping[str, Any]) -> str:
    """One of :data:`OUTCOMES` for a refinement report (``refined``, ``converged``,
    ``iterations``, ``energy_before``, ``energy_after``)."""
    if not report.get("refined"):
        return "not-refined"
    if report.get("converged"):
        return "converged"
    before, after = report.get("energy_before"), report.get("energy_after")
    progressed = before is None or after is None or after < before
    if not report.get("iterations") or not progressed:
        return "not-refined"
    return "partial"


def outcome_text(report: Mapping[str, Any]) -> str:
    """The outcome in words, e.g. ``"converged after 3 iterations"``, ``"partly: time
    limit after 2 iterations"``, ``"not refined: disabled (refine=false)"``."""
    outcome = refinement_outcome(report)
    if not report.get("refined"):
        return f"not refined: {report.get('reason', 'not run')}"
    count = int(report.get("iterations") or 0)
    iterations = f"{count} iteration" + ("" if count == 1 else "s")
    stop = STOP_WORDS.get(str(report.get("stop_reason")), str(report.get("stop_reason")))
    if outcome == "converged":
        return f"converged after {iterations}"
    if outcome == "partial":
        return f"partly: {stop} after {iterations}"
    when = "before the first iteration" if not count else f"after {iterations} with no progress"
    return f"not refined: {stop} {when}"


def with_outcome(report: dict[str, Any]) -> dict[str, Any]:
    """``report`` with its ``outcome`` and ``outcome_text`` (set in place, returned)."""
    report["outcome"] = refinement_outcome(report)
    report["outcome_text"] = outcome_text(report)
    return report


def stalled_at_targets(report: dict[str, Any]) -> dict[str, Any]:
    """``report`` told as done when it stalled (``stop_reason`` ``"stalled"``, outcome
    ``"partial"``) and its caller found the answer's quality targets met: a flattening of a
    curved surface cannot reach zero energy, so a stall there is its natural end. Its
    ``outcome_text`` then begins ``"done: quality targets met, "`` and ``targets_met`` is
    true; every other field is unchanged. Another report is returned as it is. Set in
    place, returned.

    Example:
        >>> stalled_at_targets(with_outcome({"refined": True, "converged": False,
        ...     "stop_reason": "stalled", "iterations": 16, "energy_before": 6.9,
        ...     "energy_after": 4.4}))["outcome_text"]
        'done: quality targets met, stalled (no further progress) after 16 iterations'
    """
    if report.get("outcome") != "partial" or report.get("stop_reason") != StopReason.STALLED.value:
        return report
    text = str(report.get("outcome_text", ""))
    report["targets_met"] = True
    report["outcome_text"] = "done: quality targets met, " + text.removeprefix("partly: ")
    return report


def not_refined(reason: str) -> dict[str, Any]:
    """The report of a refinement that did not run, and why (``"disabled
    (refine=false)"``, ``"exact: ..."``)."""
    return with_outcome({"refined": False, "reason": reason})
