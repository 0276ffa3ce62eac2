"""The service's time policy: how its timeouts become the solver's budgets, in one place.

A synchronous request (``FFS_REQUEST_TIMEOUT``) and a job (``FFS_JOB_TIMEOUT``) get a
wall-clock deadline when they are submitted, less a margin for encoding and sending the
answer (:meth:`TimePolicy.deadline`); the worker turns it, with an explicit
``options.max_seconds``, into the solver's :class:`~solver.core.budget.Budget`
(:meth:`TimePolicy.solver_budget`). A progressive session refines each drag for
``options.max_seconds``, else ``FFS_SESSION_SOLVE_TIMEOUT`` (:meth:`TimePolicy.drag_budget`).

Example:
    >>> TIME_POLICY.encode_margin(120.0), TIME_POLICY.encode_margin(2.0)
    (7.0, 0.5)
    >>> TIME_POLICY.drag_budget(None, 30.0), TIME_POLICY.drag_budget(2.5, 30.0)
    (30.0, 2.5)
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from solver.core.budget import Budget


@dataclass(frozen=True)
class TimePolicy:
    """The margins and defaults of the service's time budgets.

    Attributes:
        encode_seconds: seconds of every request's or job's timeout kept for encoding and
            sending its answer after the solver returns ...
        encode_share: ... plus this fraction of the timeout ...
        encode_cap: ... and at most this fraction of it.
    """

    encode_seconds: float = 1.0
    encode_share: float = 0.05
    encode_cap: float = 0.25

    def encode_margin(self, timeout: float) -> float:
        """Seconds of a ``timeout`` kept for encoding and sending the answer (120 s -> 7 s,
        10 s -> 1.5 s, 2 s -> 0.5 s)."""
        return min(self.encode_cap * timeout, self.encode_seconds + self.encode_share * timeout)

    def deadline(self, timeout: float) -> float:
        """The :func:`time.time` by which the solver must return for an answer due in
        ``timeout`` seconds from now."""
        return time.time() + timeout - self.encode_margin(timeout)

    def solver_budget(self, max_seconds: float | None, deadline: float | None) -> Budget:
        """The solver call's budget from now: the smaller of an explicit
        ``options.max_seconds`` and what is left before ``deadline`` (at least 0: a solver
        given 0 s still returns its linear answer, ``stop_reason: "time_limit"``);
        unlimited when there is neither."""
        return Budget.until(deadline).within(max_seconds)

    def drag_budget(self, max_seconds: float | None, solve_timeout: float) -> float:
        """Seconds a progressive session may refine one drag in all: its
        ``options.max_seconds``, else the backend's solve timeout
        (``FFS_SESSION_SOLVE_TIMEOUT``)."""
        return float(max_seconds or solve_timeout)


TIME_POLICY = TimePolicy()
"""The policy the service uses."""
