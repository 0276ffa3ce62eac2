"""Admission shared by the local and the Dask backends: how long to wait for a task slot,
how much a session may take, and how large a mesh one request may bring.

Request admission: a request's peak memory is predicted from its face count before it is
accepted (:class:`OperationCost`, power laws fitted to ``bench.scale``: the solver's own
models, :class:`solver.linalg.iterative.LinearSolverRules`), by the path its solver will take
(:class:`Pricing`: a reconstruction whose factors would not fit goes iterative, as the worker
hands the solver the same budget); :func:`request_memory_budget` is what one worker may use
(the machine's memory, less the sessions', shared by the workers) and :func:`faces_within` the
largest mesh an operation can take in it by either path. The face limit of each operation
follows (``FFS_MAX_REQUEST_MEMORY``, ``FFS_MAX_FACES``): beyond it 413 ``mesh-too-large``
names the memory, never an out-of-memory kill of a worker. A synchronous request's time is
predicted too (:attr:`OperationCost.first_answer`, by the path): one whose first answer would
miss ``FFS_REQUEST_TIMEOUT`` is answered 413 ``use-a-job`` (jobs have ``FFS_JOB_TIMEOUT``).

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
from solver.linalg.cost import PowerLaw
from solver.linalg.iterative import RULES as LINEAR_RULES
from solver.linalg.iterative import LinearSolverRules
from solver.refine.iterative_steps import REFINEMENT_SOLVER_RULES

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
class OperationCost:
    """What admission predicts of a request from its face count, by one solve path: its
    peak ``memory`` in bytes (the worker process included) and the seconds until its
    ``first_answer`` on this 2-core machine at load 2-3.

    The first answer is what a synchronous request cannot do without: the exact or linear
    answer (a refinement that runs out of the deadline answers its best shape so far, 200),
    so a request predicted to miss the deadline before it is answered 413 ``use-a-job``
    (:meth:`Pricing.sync_faces_within`) instead of running into a 504.
    """

    memory: PowerLaw
    first_answer: PowerLaw

    def memory_bytes(self, n_faces: int) -> int:
        """Predicted peak bytes of a request with ``n_faces`` faces."""
        return int(self.memory.at(n_faces))


FIRST_ANSWER_DIRECT = PowerLaw(per_face=3.75e-5, exponent=1.2)
"""Seconds to the linear answer of noisy forms by a factorization (``refine=False``; the
issue: 14.5 s at 388K faces, 77 s at 1.55M: exponent 1.2)."""
FIRST_ANSWER_ITERATIVE = PowerLaw(per_face=1.9e-4, exponent=1.43)
"""Seconds to the linear answer by multigrid-preconditioned CG (single-threaded: its CPU
seconds, bench.scale: 11.9 at 100K faces, 76.7 at 400K, 537-576 at 1.6M)."""
SOLVE_COST = OperationCost(memory=REFINEMENT_SOLVER_RULES.direct_memory,
                           first_answer=FIRST_ANSWER_DIRECT)
"""Operations that factorize (reconstruct where its factors fit, deform, parameterize,
interpolate, blend, transfer). Memory: the refined reconstruction of noisy forms, the
costliest of them (``REFINEMENT_SOLVER_RULES.direct_memory``: 3.8 GB at 388K faces, 18.1 GB
at 1.55M)."""
ITERATIVE_COST = OperationCost(memory=REFINEMENT_SOLVER_RULES.iterative_memory,
                               first_answer=FIRST_ANSWER_ITERATIVE)
"""A reconstruction refined by CG (``REFINEMENT_SOLVER_RULES.iterative_memory``: 560 MB at
100K faces, 1.64 GB at 400K, 5.96 GB at 1.6M); its first answer is the iterative linear
answer."""
LINEAR_COST = OperationCost(memory=LINEAR_RULES.direct_memory, first_answer=FIRST_ANSWER_DIRECT)
"""A linear reconstruction (``options.refine: false``) by a factorization (8.3 KB per face)."""
LINEAR_ITERATIVE_COST = OperationCost(memory=LINEAR_RULES.iterative_memory,
                                      first_answer=FIRST_ANSWER_ITERATIVE)
"""A linear reconstruction by CG (2.6 KB per face and 150 MB: 3.75 GiB measured at 1.6M faces)."""
LIGHT_COST = OperationCost(
    memory=PowerLaw(per_face=2_600, exponent=1.0, base=200 * 1024**2),
    first_answer=PowerLaw(per_face=1.2e-5, exponent=1.0))
"""Operations that only compute (forms, integrability, mesh): the exact path's peak
(bench.scale: 1.06 GB at 400K faces, 2.8 GB at 1.6M, 2.5 KB per face with the reading and
encoding of the arrays) and time (18 s at 1.55M faces; forms and mesh take less)."""


@dataclass(frozen=True)
class Pricing:
    """What a request of an operation costs, by the path its solver takes within the
    request's memory (FFS_MAX_REQUEST_MEMORY, which the worker hands the solver as
    ``options.memory_budget``).

    Attributes:
        direct: the cost by a factorization (or, for the light operations, the only one).
        iterative: the cost by the iterative path (None: the operation has none).
        choice: the solver's rules whose ``choose`` decides the peak's path (the
            refinement's for a refined reconstruction, Eq. 5's for a linear one); the first
            answer's path is always Eq. 5's (:data:`solver.linalg.iterative.RULES`).
    """

    direct: OperationCost
    iterative: OperationCost | None = None
    choice: LinearSolverRules = LINEAR_RULES

    def path(self, n_faces: int, memory: float) -> str:
        """``"direct"`` or ``"iterative"``: the path of the request's peak."""
        if self.iterative is None:
            return "direct"
        return self.choice.choose(n_faces, "auto", memory)

    def memory_bytes(self, n_faces: int, memory: float) -> int:
        """Predicted peak bytes of ``n_faces`` faces by the path taken within ``memory``."""
        cost = self.iterative if self.path(n_faces, memory) == "iterative" else self.direct
        return (cost or self.direct).memory_bytes(n_faces)

    def direct_faces(self, memory: float) -> int:
        """The most faces the direct path takes within ``memory``."""
        return self.direct.memory.within(memory)

    def faces_within(self, memory: float) -> int:
        """The most faces whose predicted peak, by the path the solver takes, fits
        ``memory``: the direct path's limit, or the iterative path's where it is larger
        (beyond the direct limit the solver goes iterative)."""
        fit = self.direct_faces(memory)
        if self.iterative is not None:
            fit = max(fit, self.iterative.memory.within(memory))
        return fit

    def sync_faces_within(self, seconds: float, memory: float) -> int:
        """The most faces whose first answer is predicted within ``seconds``: by a
        factorization up to Eq. 5's crossing within ``memory``, by CG beyond it."""
        if seconds <= 0:
            return 0
        direct = self.direct.first_answer.within(seconds)
        if self.iterative is None:
            return direct
        crossing = min(LINEAR_RULES.direct_memory.within(memory), LINEAR_RULES.face_threshold - 1)
        if direct <= crossing:
            return direct
        return max(crossing, self.iterative.first_answer.within(seconds))


LIGHT = Pricing(LIGHT_COST)
"""Operations that only compute."""
FACTORIZING = Pricing(SOLVE_COST)
"""Operations that factorize and have no iterative path."""
RECONSTRUCTION = Pricing(SOLVE_COST, ITERATIVE_COST, REFINEMENT_SOLVER_RULES)
"""``reconstruct``'s default answer (refined where the forms are not exact)."""
LINEAR_RECONSTRUCTION = Pricing(LINEAR_COST, LINEAR_ITERATIVE_COST, LINEAR_RULES)
"""``reconstruct`` with ``options.refine: false``."""
BODY_BYTES_PER_FACE = 100
"""Bytes per face of the largest request body FFS_MAX_BODY_BYTES makes room for by default: a
JSON forms body (faces, edges, lengths, angles: ~90 bytes per face at 17 significant
digits); a binary body takes ~50, a mesh body ~55 as JSON, a PLY upload ~20."""
MEMORY_HEADROOM = 0.8
"""Fraction of the machine's memory (less the sessions') that the workers' requests may
use together: the HTTP process, the page cache and the allocator keep the rest."""


def pricing(solves: bool, iterative: bool = False, linear: bool = False) -> Pricing:
    """The pricing of an operation that factorizes (``solves``) or only computes; one whose
    solver may go ``iterative`` (reconstruct), of its ``linear`` answer (refine false)."""
    if not solves:
        return LIGHT
    if not iterative:
        return FACTORIZING
    return LINEAR_RECONSTRUCTION if linear else RECONSTRUCTION


def sync_faces_within(seconds: float, how: Pricing, memory: float) -> int:
    """The most faces a synchronous request of an operation priced ``how`` may bring whose
    first answer is predicted within ``seconds`` (:meth:`Pricing.sync_faces_within`)."""
    return how.sync_faces_within(seconds, memory)


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


def faces_within(memory: int, how: Pricing) -> int:
    """The largest face count an operation priced ``how`` (:func:`pricing`) can take in
    ``memory`` bytes, by the path its solver takes there (:meth:`Pricing.faces_within`)."""
    return how.faces_within(memory)


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
