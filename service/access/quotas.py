"""Request quotas per key: a fixed one-minute window per key (:class:`RateLimiter`), and the
IETF ``RateLimit`` / ``RateLimit-Policy`` header fields that describe a quota
(draft-ietf-httpapi-ratelimit-headers-10: ``RateLimit-Policy: "requests";q=600;w=60``,
``RateLimit: "requests";r=599;t=42``).

The concurrent quotas (jobs, sessions per key) are counted where the jobs and sessions live
(the backends' per-owner admission, across replicas with Dask); this module only names them
(:data:`CONCURRENT_JOBS`, :data:`CONCURRENT_SESSIONS`) and formats their headers. The
request rate is counted per service process: with several API replicas each one counts its
own requests (a key gets its quota at each replica).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

WINDOW = 60.0
"""Seconds of one request-rate window."""


@dataclass(frozen=True)
class Quota:
    """A named quota in RateLimit-Policy terms: ``limit`` per ``window`` seconds
    (``unit`` ``requests``) or ``limit`` at once (``concurrent-requests``, no window)."""

    name: str
    unit: str = "requests"
    window: float | None = WINDOW

    def policy(self, limit: int) -> str:
        """The ``RateLimit-Policy`` field of this quota at ``limit``."""
        text = f'"{self.name}";q={limit}'
        if self.window is not None:
            text += f";w={math.ceil(self.window)}"
        if self.unit != "requests":
            text += f';qu="{self.unit}"'
        return text

    def state(self, remaining: int, reset: float) -> str:
        """The ``RateLimit`` field: ``remaining`` units, ``reset`` seconds until more."""
        return f'"{self.name}";r={max(0, remaining)};t={max(0, math.ceil(reset))}'

    def headers(self, limit: int, remaining: int, reset: float) -> dict[str, str]:
        return {"RateLimit-Policy": self.policy(limit),
                "RateLimit": self.state(remaining, reset)}


REQUESTS = Quota("requests")
CONCURRENT_JOBS = Quota("concurrent-jobs", "concurrent-requests", None)
CONCURRENT_SESSIONS = Quota("concurrent-sessions", "concurrent-requests", None)


@dataclass(frozen=True)
class RateDecision:
    """One request's verdict: allowed or not, and what its headers say."""

    allowed: bool
    limit: int
    remaining: int
    reset: float

    @property
    def retry_after(self) -> int:
        """Whole seconds until the window resets (at least 1)."""
        return max(1, math.ceil(self.reset))

    def headers(self) -> dict[str, str]:
        headers = REQUESTS.headers(self.limit, self.remaining, self.reset)
        if not self.allowed:
            headers["Retry-After"] = str(self.retry_after)
        return headers


class RateLimiter:
    """Requests per key name in fixed windows of :data:`WINDOW` seconds (thread-safe)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._windows: dict[str, tuple[float, int]] = {}
        self._lock = threading.Lock()

    def take(self, name: str, limit: int) -> RateDecision:
        """Count one request of ``name`` unless its window is full.

        Args:
            name: The key's name.
            limit: Its requests per window.

        Returns:
            The decision; a refused request is not counted.
        """
        now = self._clock()
        with self._lock:
            start, used = self._windows.get(name, (now, 0))
            if now - start >= WINDOW:
                start, used = now, 0
            reset = start + WINDOW - now
            if used >= limit:
                self._windows[name] = (start, used)
                return RateDecision(False, limit, 0, reset)
            used += 1
            self._windows[name] = (start, used)
            return RateDecision(True, limit, limit - used, reset)
