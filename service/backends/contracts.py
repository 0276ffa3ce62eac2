"""The backend contract: what the HTTP edge needs from a compute backend.

A backend is three collaborators sharing one set of workers (:class:`Backend`):

* an :class:`Executor` runs one :class:`~service.api.task.TaskRequest` in a worker and
  resolves a future with its :class:`~service.api.task.TaskResult`;
* a :class:`JobService` keeps asynchronous jobs (:class:`~service.backends.jobs.Job`);
* a :class:`SessionBackend` keeps deformation sessions warm with one worker each.

The local implementation lives in :mod:`service.backends.local`, the Dask one in
:mod:`service.backends.dask`; :func:`service.backends.make_backend` picks one by
``FFS_EXECUTOR``. Failures are the domain errors of :mod:`service.backends.errors`.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from service.api.task import SessionSpec, TaskRequest, TaskResult
from service.backends.admission import SessionAdmission
from service.backends.jobs import Job
from service.worker.session import Refined

ProgressCallback = Callable[..., None]
"""``progress(stage, fraction, detail=None)``: ``detail`` is the refinement's last iteration
``{"iteration", "factorizations", "energy", "seconds"}`` (see :class:`StageClock
<service.worker.runtime.StageClock>`), or None."""
StartCallback = Callable[[], None]
ResultCallback = Callable[[str, TaskResult], None]
"""``on_result(operation, result)``: a job finished (the app counts it in its metrics)."""


@dataclass
class TaskHandle:
    """A submitted task: its id and an asyncio future of its :class:`TaskResult`."""

    id: str
    future: asyncio.Future[TaskResult]


class Executor(Protocol):
    """Runs tasks in workers (local processes, or a Dask cluster)."""

    restarts: int
    """Workers replaced so far (crash, cancel, timeout)."""

    async def start(self) -> None:
        """Start the workers (called once from the app's lifespan)."""

    def begin_shutdown(self) -> None:
        """The service is stopping: replace no worker from now on."""

    async def shutdown(self) -> None:
        """Stop the workers; pending tasks fail with ``ExecutorClosedError``."""

    async def submit(self, request: TaskRequest, *, progress_cb: ProgressCallback | None = None,
                     on_start: StartCallback | None = None,
                     task_id: str | None = None) -> TaskHandle:
        """Queue ``request``; ``QueueFullError`` at once when there is no room. The future
        fails with ``TaskFailedError``, ``WorkerDiedError`` or ``TaskCancelledError``.
        ``progress_cb(stage, fraction)`` and ``on_start()`` are called on the event loop."""

    async def cancel(self, task_id: str) -> bool:
        """Cancel a queued or running task (a running one loses its worker); True if it was
        still pending."""

    def ready(self) -> bool:
        """At least one worker can take work."""

    def queue_depth(self) -> int:
        """Tasks waiting for a worker."""

    def size(self) -> int:
        """Configured number of workers."""

    def busy(self) -> int:
        """Workers running a task."""

    def workers_ready(self) -> int:
        """Workers started and idle or busy."""


class JobService(Protocol):
    """Asynchronous jobs: one task each, a record with progress, a result kept for a TTL."""

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def submit(self, request: TaskRequest, *, color: str | None = None,
                     owner: str | None = None, max_per_owner: int | None = None) -> Job:
        """Create and queue a job for ``owner`` (the client's address, or its API key),
        evicting the oldest finished jobs when the store is full; ``JobStoreFullError``,
        ``ClientJobsError`` (``owner`` has ``max_per_owner`` unfinished jobs, by default
        the policy's), ``QueueFullError`` or ``ExecutorClosedError`` when it cannot."""

    async def list(self, owner: str | None = None) -> list[Job]:
        """The stored jobs of ``owner`` (every job when None), oldest first."""

    async def get(self, job_id: str) -> Job | None:
        """The job, or None when it is unknown or expired."""

    async def result(self, job: Job) -> TaskResult:
        """The result of a succeeded job (``TaskFailedError`` if it cannot be had)."""

    async def cancel(self, job: Job) -> None:
        """Cancel a queued or running job."""

    async def delete(self, job: Job) -> None:
        """Forget a finished job and its result."""

    def counts(self) -> dict[str, int]:
        """Number of jobs per status (for the metrics)."""


@dataclass
class JobPolicy:
    """How long jobs may run and stay (``FFS_JOB_TIMEOUT``, ``FFS_JOB_TTL``), how many may
    be stored (``FFS_MAX_JOBS``) and be unfinished per client (``FFS_MAX_CLIENT_JOBS``)."""

    ttl: float
    timeout: float
    max_jobs: int
    max_per_client: int = 16


@dataclass
class SessionPolicy:
    """The session settings: idle ``ttl`` (``FFS_SESSION_TTL``), admission
    (``FFS_MAX_SESSIONS``, ``FFS_MAX_SESSION_MEMORY`` bytes), ``threads`` per session, the
    deadlines of one solve (``FFS_SESSION_SOLVE_TIMEOUT``, also a progressive drag's
    refinement budget) and of the set-up (``FFS_REQUEST_TIMEOUT``), the refinement's slice
    (``FFS_SESSION_REFINE_SLICE``), sessions per client (``FFS_MAX_CLIENT_SESSIONS``) and the
    idle seconds after which a session gives way to a new one in a full table
    (``FFS_SESSION_GIVE_WAY``). No defaults here: the settings are their one home
    (:func:`service.backends.session_policy`)."""

    ttl: float
    max_sessions: int
    max_memory: int
    threads: int
    solve_timeout: float
    setup_timeout: float
    refine_slice: float
    max_per_client: int
    give_way_after: float

    def admission(self) -> SessionAdmission:
        """The limits :func:`~service.backends.admission.admit_session` checks."""
        return SessionAdmission(self.max_sessions, self.max_memory, self.max_per_client,
                                self.give_way_after, self.ttl)


@dataclass(frozen=True)
class SessionRecord:
    """What a backend knows of a live session (rendered by the HTTP edge).

    ``info`` is :meth:`service.worker.session.SessionState.info`; ``executor`` the
    backend's name (``local`` or ``dask``)."""

    id: str
    info: dict[str, Any]
    expires_in: float
    memory: int
    solves: int
    executor: str


@dataclass(frozen=True)
class DragAnswer:
    """A drag's immediate answer: the linear shape (``body``, encoded), stage ``timings``,
    the drag's number in its session (1, 2, ...), and whether its refined shape follows
    (``refining``: a progressive session, see :meth:`SessionBackend.refined`)."""

    body: bytes
    timings: dict[str, float]
    drag: int
    refining: bool


class SessionBackend(Protocol):
    """Deformation sessions, each warm in exactly one worker. Unknown ids raise
    ``SessionNotFoundError``; expired ones and those whose worker died
    ``SessionGoneError``."""

    name: str

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def create(self, spec: SessionSpec, owner: str | None = None,
                     max_per_owner: int | None = None) -> SessionRecord:
        """Build a session for client ``owner``, who may have ``max_per_owner`` open (by
        default the policy's) (admission:
        :func:`~service.backends.admission.admit_session`, which may close idle sessions to
        make room: they answer ``SessionGoneError`` afterwards; ``ClientSessionsError``,
        ``TooManySessionsError``, ``SessionMemoryError``, ``TaskFailedError`` for a bad mesh,
        ``DeadlineError``, ``WorkerDiedError``)."""

    async def describe(self, session_id: str) -> SessionRecord: ...

    async def owner(self, session_id: str) -> str | None:
        """Who created the session (its ``owner`` at :meth:`create`), also while it is
        gone; ``SessionNotFoundError`` for an unknown id."""

    async def list(self, owner: str | None = None) -> list[SessionRecord]:
        """The live sessions of ``owner`` (every one when None)."""

    async def shape(self, session_id: str) -> tuple[int, int]:
        """(handles, rotation groups) of a session."""

    async def solve(self, session_id: str, positions: np.ndarray,
                    rotations: np.ndarray | None, fmt: str) -> DragAnswer:
        """One drag: its linear shape at once (:class:`DragAnswer`); ``DeadlineError``
        closes the session. In a progressive session the drag's refinement starts, and
        supersedes the previous drag's."""

    async def refined(self, session_id: str, drag: int, wait: float) -> Refined | None:
        """The refined shape of drag ``drag`` once ready (encoded like its linear answer),
        waiting up to ``wait`` seconds; None while it still refines. Only the newest drag's
        is kept: ``DragSupersededError`` for an older one (a newer drag stopped its
        refinement), ``DragNotFoundError`` for a drag that never was or is not refined
        (the session is not progressive), ``TaskFailedError`` when its refinement failed."""

    async def delete(self, session_id: str) -> None:
        """Close a session (a gone one is forgotten)."""

    def count(self) -> int:
        """Live sessions (as last seen)."""

    def memory(self) -> int:
        """Bytes held by live sessions (as last seen)."""


@dataclass(frozen=True)
class Backend:
    """The three collaborators of one backend, started and stopped together."""

    executor: Executor
    jobs: JobService
    sessions: SessionBackend

    async def start(self) -> None:
        await self.executor.start()
        await self.jobs.start()
        await self.sessions.start()

    async def stop(self) -> None:
        """Stop everything: no worker is replaced from here on (cancelling the running jobs
        ends their workers), sessions close, jobs are cancelled, the workers end."""
        self.executor.begin_shutdown()
        await self.sessions.stop()
        await self.jobs.stop()
        await self.executor.shutdown()
