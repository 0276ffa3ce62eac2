"""A call's time budget: created where its time starts, passed down, asked what is left.

An operation's ``max_seconds`` (a request's deadline, a job's timeout, a session drag's
refinement budget) becomes one :class:`Budget` where the call begins; everything below it
(the refinement's time limit, the share of one blend row, a deformation's refinement after
its linear solve) asks that object :meth:`Budget.left` instead of doing the arithmetic again.

Example:
    >>> budget = Budget(10.0, started=Budget.now() - 4.0)  # begun 4 s ago
    >>> round(budget.left()), round(budget.share(3).left())
    (6, 2)
    >>> Budget().left() is None, Budget(1.0, started=Budget.now() - 5.0).left()
    (True, 0.0)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Budget:
    """``seconds`` from ``started`` (:func:`time.perf_counter`); ``seconds`` None: no limit.

    Attributes:
        seconds: the budget in seconds, or None (unlimited).
        started: when it began, in :func:`time.perf_counter` seconds (default: now).
    """

    seconds: float | None = None
    started: float = field(default_factory=time.perf_counter)

    @staticmethod
    def now() -> float:
        """The clock budgets are measured on (:func:`time.perf_counter`)."""
        return time.perf_counter()

    @classmethod
    def of(cls, budget: Budget | float | None) -> Budget:
        """``budget`` itself, or a budget of that many seconds from now (None: no limit)."""
        return budget if isinstance(budget, Budget) else cls(budget)

    @classmethod
    def until(cls, deadline: float | None) -> Budget:
        """The budget up to a wall-clock ``deadline`` (:func:`time.time`, which other
        processes share; None: no limit), from now."""
        return cls(None if deadline is None else max(0.0, deadline - time.time()))

    @property
    def limited(self) -> bool:
        """Whether there is a limit."""
        return self.seconds is not None

    def spent(self) -> float:
        """Seconds since it began."""
        return time.perf_counter() - self.started

    def left(self) -> float | None:
        """Seconds left (at least 0), or None without a limit."""
        return None if self.seconds is None else max(0.0, self.seconds - self.spent())

    def out(self) -> bool:
        """Whether a limited budget has run out."""
        left = self.left()
        return left is not None and left <= 0.0

    def share(self, parts: int) -> Budget:
        """An equal share of what is left among ``parts`` calls still to come, from now."""
        left = self.left()
        return Budget(None if left is None else left / max(parts, 1))

    def within(self, seconds: float | None) -> Budget:
        """The smaller of this budget and ``seconds`` from now (None: this one)."""
        left = self.left()
        if seconds is None or (left is not None and left <= seconds):
            return self
        return Budget(seconds)
