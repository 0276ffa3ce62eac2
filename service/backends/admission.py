"""Admission shared by the local and the Dask backends: how long to wait for a task slot,
how much a session may take.

Session admission is bounded by ``FFS_MAX_SESSIONS`` (:class:`TooManySessionsError` beyond) and
``FFS_MAX_SESSION_MEMORY`` (:class:`SessionMemoryError` beyond): before a session is built
its memory is estimated from the face count (:func:`estimate_memory`); once built it is
measured and that number counts from then on.
"""

from __future__ import annotations

import math
from collections.abc import Collection

from service.backends.errors import TooManySessionsError

BYTES_PER_FACE_ESTIMATE = 6_000
"""Admission estimate of a session's memory per face before it is measured (a 20K-face
session measures about 180 MiB with PARDISO, its process included)."""
BASE_MEMORY_ESTIMATE = 80 * 1024**2
"""Admission estimate of a session process's own memory."""


def estimate_memory(n_vertices: int, n_faces: int) -> int:
    """Bytes a session of this size is expected to hold (used before it is measured)."""
    return int(BASE_MEMORY_ESTIMATE + BYTES_PER_FACE_ESTIMATE * max(n_faces, 1))


def too_many(count: int, limit: int, ttl: float) -> TooManySessionsError:
    """The refusal at ``limit`` open sessions; retry when an idle one may have expired."""
    return TooManySessionsError(count, limit, max(1, min(120, math.ceil(ttl / 4))))


def retry_after(durations: Collection[float], waiting: int, size: int) -> int:
    """Seconds until a task slot is likely free: mean recent task time x waiting tasks /
    workers (1 to 120 s)."""
    mean = (sum(durations) / len(durations)) if durations else 1.0
    return max(1, min(120, math.ceil(mean * waiting / max(1, size))))
