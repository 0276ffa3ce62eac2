"""The backends' failures, as domain errors (no HTTP here).

Backends raise these; :mod:`service.http.problems` maps each one to its problem document
(``QueueFullError`` -> 503 ``queue-full`` with Retry-After, ``SessionGoneError`` -> 410, ...).
A task's own failure travels as a failure dict (:func:`service.worker.runtime.describe_error`)
inside :class:`TaskFailedError`, and a job records its failure as such a dict
(:func:`service.api.problems.failure`).
"""

from __future__ import annotations

from typing import Any


class BackendError(Exception):
    """Base class of the backends' failures."""


class QueueFullError(BackendError):
    """No capacity: every worker busy and the queue full."""

    def __init__(self, retry_after: int) -> None:
        super().__init__(f"the work queue is full; retry after {retry_after} s")
        self.retry_after = retry_after


class ExecutorClosedError(BackendError):
    """The backend is not running (not started, shutting down, or its cluster is gone)."""


class TaskCancelledError(BackendError):
    """The task was cancelled before it finished."""


class WorkerDiedError(BackendError):
    """The worker process running the task (or holding the session) exited."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class TaskFailedError(BackendError):
    """The task raised; ``error`` is its failure dict."""

    def __init__(self, error: dict[str, Any]) -> None:
        super().__init__(str(error.get("message") or error.get("detail") or error))
        self.error = error


class DeadlineError(BackendError):
    """No result within a configured time; ``detail`` names the setting."""


class JobStoreFullError(BackendError):
    """``FFS_MAX_JOBS`` jobs are queued or running (finished ones give way to new ones)."""

    def __init__(self, count: int, limit: int) -> None:
        super().__init__(f"{count} jobs are queued or running (limit {limit}, FFS_MAX_JOBS); "
                         "retry later")
        self.count, self.limit = count, limit


class ClientJobsError(BackendError):
    """This client already has ``FFS_MAX_CLIENT_JOBS`` jobs queued or running."""

    def __init__(self, limit: int) -> None:
        super().__init__(f"this client already has {limit} jobs queued or running (the limit "
                         "per client, FFS_MAX_CLIENT_JOBS); wait for one to finish")
        self.limit = limit


class JobLostError(BackendError):
    """The job was submitted before the service last started: jobs live in the memory of the
    process that took them, and a stopping service cancels the ones still running."""

    def __init__(self, job_id: str, started_at: str) -> None:
        super().__init__(f"job {job_id} was submitted before the service restarted (at "
                         f"{started_at}); jobs are kept in memory, so its record and result "
                         "are gone: submit it again")
        self.job_id, self.started_at = job_id, started_at


class SessionNotFoundError(BackendError):
    """No such session (never created, deleted, or gone long ago)."""

    def __init__(self, session_id: str) -> None:
        super().__init__(f"no session {session_id!r} (it may have been deleted, or it expired "
                         "long ago)")
        self.session_id = session_id


class SessionGoneError(BackendError):
    """The session expired or its worker died; ``reason`` says which."""

    def __init__(self, session_id: str, reason: str) -> None:
        super().__init__(f"session {session_id} is gone: {reason}; create a new one")
        self.session_id, self.reason = session_id, reason


class DragNotFoundError(BackendError):
    """A session has no refined shape for that drag (no such drag, or it does not refine)."""

    def __init__(self, session_id: str, drag: int, reason: str) -> None:
        super().__init__(f"session {session_id} has no refined shape of drag {drag}: {reason}")
        self.session_id, self.drag = session_id, drag


class DragSupersededError(BackendError):
    """A newer drag replaced this one before (or after) its refinement finished: only the
    newest drag's refined shape is computed and kept."""

    def __init__(self, session_id: str, drag: int, latest: int) -> None:
        super().__init__(f"drag {drag} of session {session_id} was superseded by drag "
                         f"{latest}: only the newest drag is refined")
        self.session_id, self.drag, self.latest = session_id, drag, latest


class TooManySessionsError(BackendError):
    """``FFS_MAX_SESSIONS`` sessions are open."""

    def __init__(self, count: int, limit: int, retry_after: int) -> None:
        super().__init__(f"{count} sessions are open (limit {limit}, FFS_MAX_SESSIONS); delete "
                         "one or wait until an idle one expires")
        self.count, self.limit, self.retry_after = count, limit, retry_after


class ClientSessionsError(BackendError):
    """This client already has ``FFS_MAX_CLIENT_SESSIONS`` sessions open."""

    def __init__(self, limit: int) -> None:
        super().__init__(f"this client already has {limit} sessions open (the limit per "
                         "client, FFS_MAX_CLIENT_SESSIONS); delete one or let one expire")
        self.limit = limit


class SessionMemoryError(BackendError):
    """The open sessions and a new one would exceed ``FFS_MAX_SESSION_MEMORY``."""

    def __init__(self, used: int, needed: int, limit: int) -> None:
        super().__init__(f"sessions hold {used / 2**20:.0f} MiB and this one needs about "
                         f"{needed / 2**20:.0f} MiB more; the limit is {limit / 2**20:.0f} MiB "
                         "(FFS_MAX_SESSION_MEMORY)")
        self.used, self.needed, self.limit = used, needed, limit
