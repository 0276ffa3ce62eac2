"""The backends' failures, as domain errors (no HTTP here).

Backends raise these; :func:`service.http.problems.problem_for` maps each one to its problem
document (``QueueFullError`` -> 503 ``queue-full`` with Retry-After, ``SessionGoneError``
-> 410, ...). A task's own failure travels as a failure dict
(:func:`service.api.problems.failure_of`) inside :class:`TaskFailedError`, and a job
records its failure as such a dict (:func:`service.api.problems.failure`).

Most failures are described by their fields (:class:`DescribedError`): a dataclass whose
``template`` (a :meth:`str.format` string over the fields) is its message, constructed
positionally (``ClientJobsError(limit)``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, ClassVar


class BackendError(Exception):
    """Base class of the backends' failures."""


class ExecutorClosedError(BackendError):
    """The backend is not running (not started, shutting down, or its cluster is gone)."""


class TaskCancelledError(BackendError):
    """The task was cancelled before it finished."""


class DeadlineError(BackendError):
    """No result within a configured time; the message names the setting."""


class TaskFailedError(BackendError):
    """The task raised.

    Args:
        error: Its failure dict (a problem document without ``instance``).
    """

    def __init__(self, error: dict[str, Any]) -> None:
        super().__init__(str(error.get("detail") or error))
        self.error = error


@dataclass(eq=False)
class DescribedError(BackendError):
    """A failure described by its fields: ``str()`` is ``template`` filled with them.

    Every subclass is a dataclass of the fields it declares (``__init_subclass__``).
    """

    template: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        dataclass(eq=False)(cls)

    def __post_init__(self) -> None:
        super().__init__(str(self))

    def __str__(self) -> str:
        return self.template.format_map(vars(self))

    def __reduce__(self) -> tuple[Any, ...]:
        return type(self), tuple(getattr(self, f.name) for f in fields(self))


class QueueFullError(DescribedError):
    """No capacity: every worker busy and the queue full."""

    retry_after: int
    template = "the work queue is full; retry after {retry_after} s"


class WorkerDiedError(DescribedError):
    """The worker process running the task (or holding the session) exited."""

    reason: str
    template = "{reason}"


class JobStoreFullError(DescribedError):
    """``FFS_MAX_JOBS`` jobs are queued or running (finished ones give way to new ones)."""

    count: int
    limit: int
    template = "{count} jobs are queued or running (limit {limit}, FFS_MAX_JOBS); retry later"


class ClientJobsError(DescribedError):
    """This client already has ``FFS_MAX_CLIENT_JOBS`` jobs queued or running."""

    limit: int
    template = ("this client already has {limit} jobs queued or running (the limit per "
                "client, FFS_MAX_CLIENT_JOBS); wait for one to finish")


class JobLostError(DescribedError):
    """The job was submitted before the service last started: jobs live in the memory of the
    process that took them, and a stopping service cancels the ones still running."""

    job_id: str
    started_at: str
    template = ("job {job_id} was submitted before the service restarted (at {started_at}); "
                "jobs are kept in memory, so its record and result are gone: submit it again")


class SessionNotFoundError(DescribedError):
    """No such session (never created, deleted, or gone long ago)."""

    session_id: str
    template = "no session {session_id!r} (it may have been deleted, or it expired long ago)"


class SessionGoneError(DescribedError):
    """The session expired or its worker died; ``reason`` says which."""

    session_id: str
    reason: str
    template = "session {session_id} is gone: {reason}; create a new one"


class TooManySessionsError(DescribedError):
    """``FFS_MAX_SESSIONS`` sessions are open."""

    count: int
    limit: int
    retry_after: int
    template = ("{count} sessions are open (limit {limit}, FFS_MAX_SESSIONS); delete one or "
                "wait until an idle one expires")


class ClientSessionsError(DescribedError):
    """This client already has ``FFS_MAX_CLIENT_SESSIONS`` sessions open."""

    limit: int
    template = ("this client already has {limit} sessions open (the limit per client, "
                "FFS_MAX_CLIENT_SESSIONS); delete one or let one expire")


class SessionMemoryError(DescribedError):
    """The open sessions and a new one would exceed ``FFS_MAX_SESSION_MEMORY`` (bytes)."""

    used: int
    needed: int
    limit: int

    def __str__(self) -> str:
        mib = 2**20
        return (f"sessions hold {self.used / mib:.0f} MiB and this one needs about "
                f"{self.needed / mib:.0f} MiB more; the limit is {self.limit / mib:.0f} MiB "
                "(FFS_MAX_SESSION_MEMORY)")


class DragNotFoundError(DescribedError):
    """A session has no refined shape for that drag (no such drag, or it does not refine)."""

    session_id: str
    drag: int
    reason: str
    template = "session {session_id} has no refined shape of drag {drag}: {reason}"


class DragSupersededError(DescribedError):
    """A newer drag replaced this one before (or after) its refinement finished: only the
    newest drag's refined shape is computed and kept."""

    session_id: str
    drag: int
    latest: int
    template = ("drag {drag} of session {session_id} was superseded by drag {latest}: only the "
                "newest drag is refined")
