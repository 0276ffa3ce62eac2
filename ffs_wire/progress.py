"""The one rule of progress reports, wherever a task runs: a service's local worker, a Dask
worker (:func:`service.operations.run`) and a local worker process of ``ffs -j N``
(:func:`ffs.cli.batch.run_item`) send at most one report per :data:`PROGRESS_INTERVAL`,
the first and the last always (:class:`ProgressThrottle`). Standard library only.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

Send = Callable[..., None]
"""``send(stage, fraction, detail=None)``: where the reports go."""

PROGRESS_INTERVAL = 0.2
"""Seconds between two progress reports a task sends out of its worker (at most 5 a second,
whatever the backend: a local worker's pipe, a Dask worker's scheduler events or an ``ffs``
worker process's queue); the first report and the last always go (:class:`ProgressThrottle`)."""


class ProgressThrottle:
    """``progress(stage, fraction, detail=None)`` passed on at most once per
    :data:`PROGRESS_INTERVAL`, the one rule of every backend's progress (an atlas of 56K
    charts reports each chart; its job needs a few reports a second).

    A report goes on at once when it is the first, when its stage differs from the last one
    sent, or when the interval has passed since then; otherwise it is held, the newest
    replacing the older, and a refinement iteration's ``detail`` held with it goes on with
    the next report sent. :meth:`flush` sends what is held: the task's last report (e.g.
    ``("encode", 1.0)``) always arrives.

    Args:
        send: The backend's ``progress(stage, fraction, detail=None)``.
        interval: Seconds between two reports (:data:`PROGRESS_INTERVAL`).
        clock: The time in seconds (``time.monotonic``).

    Example:
        >>> sent, now = [], [0.0]
        >>> throttle = ProgressThrottle(lambda *report: sent.append(report),
        ...                             clock=lambda: now[0])
        >>> for k in range(1000):
        ...     throttle("charts", k / 999)
        >>> throttle.flush()
        >>> sent
        [('charts', 0.0, None), ('charts', 1.0, None)]
    """

    def __init__(self, send: Send, interval: float = PROGRESS_INTERVAL,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._send, self._interval, self._clock = send, interval, clock
        self._stage: str | None = None
        self._last: float | None = None
        self._held: tuple[str, float] | None = None
        self._detail: dict[str, Any] | None = None

    def __call__(self, stage: str, fraction: float,
                 detail: dict[str, Any] | None = None) -> None:
        if detail is not None:
            self._detail = detail
        now = self._clock()
        if (self._last is None or stage != self._stage
                or now - self._last >= self._interval):
            self._deliver(stage, fraction, now)
        else:
            self._held = (stage, fraction)

    def flush(self) -> None:
        """Send the report held back, if any (the task's last)."""
        if self._held is not None:
            self._deliver(*self._held, self._clock())

    def _deliver(self, stage: str, fraction: float, now: float) -> None:
        detail, self._detail, self._held = self._detail, None, None
        self._stage, self._last = stage, now
        self._send(stage, fraction, detail)


__all__ = ["PROGRESS_INTERVAL", "ProgressThrottle", "Send"]
