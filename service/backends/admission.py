"""Admission shared by the local and the Dask backends: how long to wait for a task slot,
how much a session may take, and how large a mesh one request may bring.

Request admission: a request's peak memory is predicted from its face count before it is
accepted (:class:`OperationCost`, power laws fitted to ``bench.scale``);
:func:`request_memory_budget` is what one worker may use (the machine's memory, less the
sessions', shared by the workers) and :func:`faces_within` the largest mesh an operation can
take in it. The face limit of each operation follows (``FFS_MAX_REQUEST_MEMORY``,
``FFS_MAX_FACES``): beyond it 413 ``mesh-too-large`` names the memory, never an
out-of-memory kill of a worker. A synchronous request's time is predicted too
(:attr:`OperationCost.first_answer`): one whose first answer would miss
``FFS_REQUEST_TIMEOUT`` is answered 413 ``use-a-job`` (jobs have ``FFS_JOB_TIMEOUT``).

Session admission (:func:`admit_session`) is bounded by ``FFS_MAX_SESSIONS``
(:class:`TooManySessionsError` beyond), ``FFS_MAX_SESSION_MEMORY`` (:class:`SessionMemoryError`
beyond) and ``FFS_MAX_CLIENT_SESSIONS`` per client address (:class:`ClientSessionsError`):
before a session is built its memory is estimated from the face count
(:func:`estimate_memory`); once built it is measured and that number counts from then on.
When the table (or the memory) is full, sessions idle for ``FFS_SESSION_GIVE_WAY`` seconds or
more give way, the longest idle first, before a new one is refused.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable
from dataclasses import dataclass

from service.backends.errors import ClientSessionsError, SessionMemoryError, TooManySessionsError

BYTES_PER_FACE_ESTIMATE = 6_000
"""Admission estimate of a session's memory per face before it is measured (a 20K-face
session measures about 180 MiB with PARDISO, its process included)."""
BASE_MEMORY_ESTIMATE = 80 * 1024**2
"""Admission estimate of a session process's own memory."""


def estimate_memory(n_vertices: int, n_faces: int) -> int:
    """The memory a session is expected to hold before it is measured.

    Args:
        n_vertices: its mesh's vertex count (unused: faces dominate).
        n_faces: its mesh's face count.

    Returns:
        Bytes: :data:`BASE_MEMORY_ESTIMATE` plus :data:`BYTES_PER_FACE_ESTIMATE` per face.
    """
    return int(BASE_MEMORY_ESTIMATE + BYTES_PER_FACE_ESTIMATE * max(n_faces, 1))


@dataclass(frozen=True)
class PowerLaw:
    """A cost that grows as a power of the face count: ``base + per_face * m * (m /
    reference)^(exponent - 1)`` for m faces, fitted through two measured points (bench.scale,
    nefertiti subdivided). The one model of admission: bytes of peak memory
    (:attr:`OperationCost.memory`) and seconds to the first answer
    (:attr:`OperationCost.first_answer`).

    Example:
        >>> PowerLaw(per_face=2.0, exponent=1.0).at(1000)
        2000.0
        >>> PowerLaw(per_face=2.0, exponent=1.0).within(2001.0)
        1000
    """

    per_face: float
    exponent: float
    reference: int = 400_000
    base: float = 0.0

    def at(self, n_faces: int) -> float:
        """The predicted cost of ``n_faces`` faces."""
        m = max(n_faces, 1)
        return self.base + self.per_face * m * (m / self.reference) ** (self.exponent - 1)

    def within(self, budget: float) -> int:
        """The most faces whose predicted cost stays within ``budget`` (0 when even the base
        does not fit)."""
        room = budget - self.base
        if room <= 0:
            return 0
        # per_face * m^exponent / reference^(exponent - 1) = room
        scale = self.per_face / self.reference ** (self.exponent - 1)
        return int((room / scale) ** (1 / self.exponent))


@dataclass(frozen=True)
class OperationCost:
    """What admission predicts of a request from its face count: its peak ``memory`` in
    bytes (the worker process included) and the seconds until its ``first_answer`` on this
    2-core machine at load 2-3.

    The first answer is what a synchronous request cannot do without: the exact or linear
    answer (a refinement that runs out of the deadline answers its best shape so far, 200),
    so a request predicted to miss the deadline before it is answered 413 ``use-a-job``
    (:func:`sync_faces_within`) instead of running into a 504.
    """

    memory: PowerLaw
    first_answer: PowerLaw

    def memory_bytes(self, n_faces: int) -> int:
        """Predicted peak bytes of a request with ``n_faces`` faces."""
        return int(self.memory.at(n_faces))


SOLVE_COST = OperationCost(
    memory=PowerLaw(per_face=9_800, exponent=1.13, base=200 * 1024**2),
    first_answer=PowerLaw(per_face=3.75e-5, exponent=1.2))
"""Operations that factorize (reconstruct, deform, parameterize, interpolate, blend,
transfer). Memory: the refined reconstruction of noisy forms, the costliest of them
(bench.scale, nefertiti subdivided: 3.8 GB at 388K faces, 18.1 GB at 1.55M). First answer:
the linear answer of noisy forms (``refine=False``; 14.5 s at 388K faces, 77 s at 1.55M:
exponent 1.2)."""
LIGHT_COST = OperationCost(
    memory=PowerLaw(per_face=2_600, exponent=1.0, base=200 * 1024**2),
    first_answer=PowerLaw(per_face=1.2e-5, exponent=1.0))
"""Operations that only compute (forms, integrability, mesh): the exact path's peak
(bench.scale: 1.06 GB at 400K faces, 2.8 GB at 1.6M, 2.5 KB per face with the reading and
encoding of the arrays) and time (18 s at 1.55M faces; forms and mesh take less)."""
BODY_BYTES_PER_FACE = 100
"""Bytes per face of the largest request body FFS_MAX_BODY_BYTES makes room for by default: a
JSON forms body (faces, edges, lengths, angles: ~90 bytes per face at 17 significant
digits); a binary body takes ~50, a mesh body ~55 as JSON, a PLY upload ~20."""
MEMORY_HEADROOM = 0.8
"""Fraction of the machine's memory (less the sessions') that the workers' requests may
use together: the HTTP process, the page cache and the allocator keep the rest."""


def request_cost(solves: bool) -> OperationCost:
    """The cost model of an operation that factorizes (``solves``) or only computes."""
    return SOLVE_COST if solves else LIGHT_COST


def sync_faces_within(seconds: float, solves: bool) -> int:
    """The most faces a synchronous request of an operation (``solves``: one that
    factorizes) may bring whose first answer is predicted within ``seconds``."""
    return request_cost(solves).first_answer.within(seconds) if seconds > 0 else 0


DASK_REQUEST_MEMORY = 4 * 1024**3
"""FFS_MAX_REQUEST_MEMORY's default with ``FFS_EXECUTOR=dask``: requests run on the cluster's
workers, not on this machine (``docker-compose.yml`` gives each ``--memory-limit 4GiB``)."""
MIN_REQUEST_MEMORY = 1024**3
"""The least FFS_MAX_REQUEST_MEMORY defaults to (about 80K faces for a reconstruction)."""


def request_memory_budget(machine_memory: int, session_memory: int, workers: int) -> int:
    """Bytes one request may use: :data:`MEMORY_HEADROOM` of the machine's memory less the
    sessions' (``FFS_MAX_SESSION_MEMORY``; at most half of it is set aside for them), shared
    by ``workers`` solving at once; at least :data:`MIN_REQUEST_MEMORY`."""
    room = MEMORY_HEADROOM * max(machine_memory - session_memory, machine_memory / 2)
    return max(int(room / max(workers, 1)), MIN_REQUEST_MEMORY)


def faces_within(memory: int, solves: bool) -> int:
    """The largest face count an operation (``solves``: one that factorizes) can take in
    ``memory`` bytes (:attr:`OperationCost.memory`)."""
    return request_cost(solves).memory.within(memory)


@dataclass(frozen=True)
class SessionSlot:
    """What admission needs of an open (or reserved) session: its client ``owner``, the
    ``memory`` it counts for, and ``idle`` seconds since its last drag (``None`` while it is
    being built or is answering a drag: it never gives way then)."""

    id: str
    owner: str | None
    memory: int
    idle: float | None


@dataclass(frozen=True)
class SessionAdmission:
    """Limits of :func:`admit_session` (from :class:`~service.backends.contracts.SessionPolicy`)."""

    max_sessions: int
    max_memory: int
    max_per_owner: int
    give_way_after: float
    ttl: float


def admit_session(slots: Iterable[SessionSlot], owner: str | None, estimate: int,
                  limits: SessionAdmission) -> list[str]:
    """The sessions to close so that a new one fits.

    Args:
        slots: the open and reserved sessions.
        owner: the new session's client address, or None.
        estimate: the new session's expected bytes (:func:`estimate_memory`).
        limits: the limits.

    Returns:
        The ids to close: none when it fits as it is; else sessions idle for at least
        ``limits.give_way_after`` seconds, the longest idle first, as many as needed.

    Raises:
        ClientSessionsError: ``owner`` already has ``max_per_owner`` sessions (its own idle
            ones do not give way: it may delete them).
        TooManySessionsError: not enough sessions may give way to fit the count (none is
            closed then).
        SessionMemoryError: not enough sessions may give way to fit the memory.
    """
    slots = list(slots)
    if owner is not None and sum(s.owner == owner for s in slots) >= limits.max_per_owner:
        raise ClientSessionsError(limits.max_per_owner)
    idle = sorted((s for s in slots if s.idle is not None and s.idle >= limits.give_way_after),
                  key=lambda s: -(s.idle or 0.0))
    count, used, evict = len(slots), sum(s.memory for s in slots), []
    while count >= limits.max_sessions or used + estimate > limits.max_memory:
        if not idle:
            if count >= limits.max_sessions:
                raise TooManySessionsError(len(slots), limits.max_sessions,
                                           _session_retry_after(slots, limits))
            raise SessionMemoryError(sum(s.memory for s in slots), estimate, limits.max_memory)
        victim = idle.pop(0)
        evict.append(victim.id)
        count, used = count - 1, used - victim.memory
    return evict


def _session_retry_after(slots: list[SessionSlot], limits: SessionAdmission) -> int:
    """Seconds until the longest idle session may give way (or, with none idle, until an
    idle one may have expired), 1 to 120."""
    idle = [s.idle for s in slots if s.idle is not None]
    wait = limits.give_way_after - max(idle) if idle else limits.ttl / 4
    return max(1, min(120, math.ceil(min(wait, limits.ttl / 4))))


def retry_after(durations: Collection[float], waiting: int, size: int) -> int:
    """Seconds until a task slot is likely free.

    Args:
        durations: recent task durations (seconds).
        waiting: tasks waiting for a slot.
        size: workers.

    Returns:
        Mean recent task time x waiting tasks / workers, rounded up, within 1 to 120.
    """
    mean = (sum(durations) / len(durations)) if durations else 1.0
    return max(1, min(120, math.ceil(mean * waiting / max(1, size))))
