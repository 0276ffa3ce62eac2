"""Jobs on the service (``/v1/jobs``): :class:`Job`, what :meth:`ffs.Client.submit` returns,
polled for its :class:`JobProgress` and its result."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ffs.errors import (
    GoneError,
    JobCancelledError,
    NotFoundError,
    RequestTimeoutError,
    ServiceUnreachableError,
    problem_error,
)

if TYPE_CHECKING:
    from ffs.client import Client, Progress


@dataclass(frozen=True)
class JobProgress:
    """A job's state: ``status`` (queued, running, succeeded, failed, cancelled), the
    current ``stage``, the overall ``fraction`` and each stage's fraction."""

    status: str
    stage: str | None
    fraction: float
    stages: dict[str, float]

    @property
    def done(self) -> bool:
        return self.status in ("succeeded", "failed", "cancelled")


class Job:
    """A job on the service (:meth:`Client.submit`)."""

    POLL_FIRST = 0.02
    POLL_MAX = 0.5

    def __init__(self, client: Client, job_id: str, operation: str,
                 decode: Callable[[dict[str, Any]], Any], document: dict[str, Any] | None
                 ) -> None:
        self.client = client
        self.id = job_id
        self.operation = operation
        self._decode = decode
        self.document = document or {}
        self.path = f"/v1/jobs/{job_id}"

    def __repr__(self) -> str:
        return f"Job({self.id!r}, {self.operation!r})"

    def status(self) -> dict[str, Any]:
        """The job document (``GET /v1/jobs/{id}``)."""
        self.document = dict(self.client.request("GET", self.path).json())
        return self.document

    def progress(self) -> JobProgress:
        """The job's status and progress now."""
        doc = self.status()
        progress = doc.get("progress") or {}
        return JobProgress(str(doc["status"]), progress.get("stage"),
                           float(progress.get("fraction") or 0.0),
                           dict(progress.get("stages") or {}))

    def wait(self, timeout: float | None = None, on_progress: Progress | None = None
             ) -> JobProgress:
        """Poll until the job finished (at most ``timeout`` seconds: then
        :class:`~ffs.errors.RequestTimeoutError`), calling ``on_progress(stage, fraction)``."""
        deadline = None if timeout is None else time.monotonic() + timeout
        interval = self.POLL_FIRST
        while True:
            state = self.progress()
            if on_progress is not None:
                _report(state, on_progress)
            if state.done:
                return state
            if deadline is not None and time.monotonic() > deadline:
                raise RequestTimeoutError(f"job {self.id} still {state.status} after {timeout:g} s")
            time.sleep(interval)
            interval = min(self.POLL_MAX, interval * 1.5)

    def result(self, timeout: float | None = None, on_progress: Progress | None = None) -> Any:
        """Wait, then the result (the operation's result type). A failed job raises the
        typed error of its problem document; a cancelled one :class:`JobCancelledError`."""
        state = self.wait(timeout, on_progress)
        if state.status == "cancelled":
            raise JobCancelledError(f"job {self.id} was cancelled")
        if state.status == "failed":
            error = self.document.get("error") or {"title": "Job failed", "status": 500}
            raise problem_error(error, int(error.get("status") or 500))
        response = self.client.request("GET", f"{self.path}/result",
                                       headers={"Accept": "application/json"})
        return self._decode(response.json())

    def cancel(self) -> None:
        """Cancel a queued or running job (a finished one is deleted with its result)."""
        self.client.request("DELETE", self.path)

    def discard(self) -> None:
        """Delete the job and its result on the service (or cancel it); a job already gone
        is fine."""
        with contextlib.suppress(NotFoundError, GoneError, ServiceUnreachableError):
            self.cancel()


def _report(state: JobProgress, on_progress: Progress) -> None:
    """Call ``on_progress`` with the job's stage (``queued`` while it waits): a job that is
    running or done but has no stage yet (between its start and its first progress event) is
    not reported, so that a caller sees only the stage names
    :data:`ffs.client.Progress` names, never a status such as ``running``."""
    if state.status == "queued":
        on_progress("queued", 0.0)
    elif state.stage:
        on_progress(state.stage, state.stages.get(state.stage, 0.0))
