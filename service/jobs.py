"""Asynchronous jobs: a store (in memory now, behind :class:`JobStore`) and a manager.

A job runs one operation on the executor. Its record holds the state (queued, running,
succeeded, failed, cancelled), per-stage progress fractions and timings, the error as a
problem document, and the result (the encoded JSON body plus the mesh arrays so that
``GET /v1/jobs/{id}/result`` can return glTF or add colours). Finished jobs expire
``FFS_JOB_TTL`` seconds after they finish; a sweeper removes them.

The routes talk to a :class:`JobService`: :class:`JobManager` here (local executor, jobs in
this process) or :class:`service.cluster.DaskJobManager` (jobs on a Dask cluster, their
state in the scheduler so that every service replica sees them).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Protocol

from service.executor import (
    Executor,
    ExecutorClosedError,
    QueueFullError,
    TaskCancelledError,
    TaskFailedError,
    WorkerDiedError,
)
from service.problems import ProblemError, from_worker_error
from service.tasks import STAGES

logger = logging.getLogger("service.jobs")

TERMINAL = ("succeeded", "failed", "cancelled")


def _iso(timestamp: float | None) -> str | None:
    if timestamp is None:
        return None
    return datetime.fromtimestamp(timestamp, UTC).isoformat(timespec="milliseconds").replace(
        "+00:00", "Z")


@dataclass
class Job:
    """One asynchronous job (times are ``time.time()`` seconds)."""

    id: str
    operation: str
    color: str | None = None
    status: str = "queued"
    created_at: float = field(default_factory=time.time)
    started_at: float | None = None
    finished_at: float | None = None
    expires_at: float | None = None
    stages: dict[str, float] = field(default_factory=dict)
    stage: str | None = None
    stage_started: float | None = None
    timings: dict[str, float] = field(default_factory=dict)
    error: dict[str, Any] | None = None
    result: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if not self.stages:
            self.stages = dict.fromkeys(STAGES.get(self.operation, ("solve",)), 0.0)

    @property
    def done(self) -> bool:
        return self.status in TERMINAL

    def mark_running(self) -> None:
        if self.status == "queued":
            self.status = "running"
            self.started_at = time.time()
            self.timings["queued"] = self.started_at - self.created_at

    def update_progress(self, stage: str, fraction: float) -> None:
        """Record ``progress(stage, fraction)``: earlier stages are complete, later ones are
        not (a solver may go back, e.g. from a failed shortcut to the factorization)."""
        if self.done:
            return
        self.mark_running()
        now = time.time()
        previous = self.stage
        if stage != self.stage:
            if self.stage is not None and self.stage_started is not None:
                self.timings[self.stage] = (self.timings.get(self.stage, 0.0)
                                            + now - self.stage_started)
            self.stage, self.stage_started = stage, now
        names = list(self.stages)
        if stage not in names:
            return
        at = names.index(stage)
        fraction = min(1.0, max(0.0, fraction))
        if previous in names and names.index(previous) > at:
            # Back to an earlier stage (e.g. the tree integration reported `solve`, did not
            # reproduce the forms, and the solver now factorizes): the later stages are not
            # done, and this one is only as far as it says.
            for later in names[at:]:
                self.stages[later] = 0.0
        for earlier in names[:at]:
            self.stages[earlier] = 1.0
        self.stages[stage] = max(self.stages[stage], fraction)

    def finish(self, status: str, ttl: float) -> None:
        now = time.time()
        if self.stage is not None and self.stage_started is not None and status == "succeeded":
            self.timings.setdefault(self.stage, now - self.stage_started)
        self.status = status
        self.finished_at = now
        self.expires_at = now + ttl
        if status == "succeeded":
            self.stages = dict.fromkeys(self.stages, 1.0)
        self.stage_started = None

    @property
    def fraction(self) -> float:
        """Overall progress in [0, 1]: mean of the stage fractions."""
        if self.status == "succeeded":
            return 1.0
        return sum(self.stages.values()) / max(1, len(self.stages))

    def to_status(self) -> dict[str, Any]:
        """The ``GET /v1/jobs/{id}`` document."""
        base = f"/v1/jobs/{self.id}"
        return {
            "id": self.id, "operation": self.operation, "status": self.status,
            "progress": {"stage": self.stage, "fraction": round(self.fraction, 4),
                         "stages": dict(self.stages)},
            "timings": dict(self.timings),
            "created_at": _iso(self.created_at), "started_at": _iso(self.started_at),
            "finished_at": _iso(self.finished_at), "expires_at": _iso(self.expires_at),
            "error": self.error,
            "links": {"self": base, "result": f"{base}/result"},
        }


class JobStore(Protocol):
    """Where jobs live. The in-memory store is per process; a shared one could replace it."""

    def add(self, job: Job) -> None: ...

    def get(self, job_id: str) -> Job | None: ...

    def remove(self, job_id: str) -> None: ...

    def expired(self, now: float) -> list[str]:
        """Ids of finished jobs whose TTL has passed."""

    def __len__(self) -> int: ...

    def counts(self) -> dict[str, int]:
        """Number of jobs per status."""


class MemoryJobStore:
    """A dict of jobs (the default :class:`JobStore`)."""

    def __init__(self) -> None:
        self._jobs: dict[str, Job] = {}

    def add(self, job: Job) -> None:
        self._jobs[job.id] = job

    def get(self, job_id: str) -> Job | None:
        return self._jobs.get(job_id)

    def remove(self, job_id: str) -> None:
        self._jobs.pop(job_id, None)

    def expired(self, now: float) -> list[str]:
        return [j.id for j in self._jobs.values()
                if j.expires_at is not None and j.expires_at <= now]

    def __len__(self) -> int:
        return len(self._jobs)

    def counts(self) -> dict[str, int]:
        out = dict.fromkeys(("queued", "running", *TERMINAL), 0)
        for job in self._jobs.values():
            out[job.status] += 1
        return out


class JobService(Protocol):
    """What the job routes need (local: :class:`JobManager`; Dask: ``DaskJobManager``)."""

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def submit(self, operation: str, payload: dict[str, Any], *,
                     color: str | None = None, task: str | None = None) -> Job:
        """Create and queue a job; 503 problems when the queue or the store is full."""

    async def get(self, job_id: str) -> Job | None:
        """The job, or None when it is unknown or expired."""

    async def result(self, job: Job) -> dict[str, Any]:
        """The result dict of a succeeded job (see :mod:`service.tasks`)."""

    async def cancel(self, job: Job) -> None:
        """Cancel a queued or running job."""

    async def delete(self, job: Job) -> None:
        """Forget a finished job and its result."""

    def counts(self) -> dict[str, int]:
        """Number of jobs per status (for the metrics)."""


class JobManager:
    """Runs jobs on the executor and keeps their records in a :class:`JobStore`."""

    def __init__(self, store: JobStore, executor: Executor, *, ttl: float, timeout: float,
                 max_jobs: int, on_result: Any = None) -> None:
        self.store = store
        self.executor = executor
        self.ttl = ttl
        self.timeout = timeout
        self.max_jobs = max_jobs
        self._on_result = on_result
        self._runners: dict[str, asyncio.Task[None]] = {}
        self._sweeper: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._sweeper = asyncio.create_task(self._sweep())

    async def stop(self) -> None:
        tasks = [t for t in (self._sweeper, *self._runners.values()) if t is not None]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

    def expire(self) -> int:
        """Remove expired jobs now; returns how many."""
        ids = self.store.expired(time.time())
        for job_id in ids:
            self.store.remove(job_id)
        return len(ids)

    async def _sweep(self) -> None:
        interval = max(0.05, min(30.0, self.ttl / 4))
        while True:
            await asyncio.sleep(interval)
            try:
                self.expire()
            except Exception:
                logger.exception("job sweeper failed")

    async def submit(self, operation: str, payload: dict[str, Any], *, color: str | None = None,
                     task: str | None = None) -> Job:
        """Create a job and queue it; raises a 503 problem when the queue or store is full."""
        self.expire()
        if len(self.store) >= self.max_jobs:
            raise ProblemError("too-many-jobs",
                               f"{len(self.store)} jobs are stored (limit {self.max_jobs}); "
                               "fetch or delete finished jobs, or retry later",
                               headers={"Retry-After": "5"})
        job = Job(id=uuid.uuid4().hex, operation=operation, color=color)
        try:
            handle = await self.executor.submit(
                task or operation, payload, task_id=job.id, progress_cb=job.update_progress,
                on_start=job.mark_running)
        except QueueFullError as exc:
            raise queue_full_problem(exc) from exc
        except ExecutorClosedError as exc:
            raise ProblemError("unavailable", str(exc), headers={"Retry-After": "5"}) from exc
        self.store.add(job)
        self._runners[job.id] = asyncio.create_task(self._run(job, handle.future))
        return job

    async def _run(self, job: Job, future: asyncio.Future[Any]) -> None:
        try:
            result = await asyncio.wait_for(asyncio.shield(future), self.timeout)
        except TimeoutError:
            await self.executor.cancel(job.id)
            self._fail(job, ProblemError("timeout", f"the job did not finish within "
                                         f"{self.timeout:g} s (FFS_JOB_TIMEOUT)"))
        except TaskCancelledError:
            if not job.done:
                job.finish("cancelled", self.ttl)
        except TaskFailedError as exc:
            self._fail(job, from_worker_error(exc.error))
        except WorkerDiedError as exc:
            self._fail(job, ProblemError("worker-died", exc.reason))
        except ExecutorClosedError as exc:
            self._fail(job, ProblemError("unavailable", str(exc)))
        except asyncio.CancelledError:
            await self.executor.cancel(job.id)
            if not job.done:
                job.finish("cancelled", self.ttl)
            raise
        else:
            if not job.done:
                job.result = result
                job.finish("succeeded", self.ttl)
                if self._on_result is not None:
                    self._on_result(job.operation, result)
        finally:
            self._runners.pop(job.id, None)

    async def get(self, job_id: str) -> Job | None:
        return self.store.get(job_id)

    async def result(self, job: Job) -> dict[str, Any]:
        if job.result is None:
            raise ProblemError("job-failed", f"job {job.id} has no result")
        return job.result

    async def delete(self, job: Job) -> None:
        self.store.remove(job.id)

    def counts(self) -> dict[str, int]:
        return self.store.counts()

    def _fail(self, job: Job, problem: ProblemError) -> None:
        if job.done:
            return
        job.error = problem.to_dict(f"/v1/jobs/{job.id}")
        job.finish("failed", self.ttl)

    async def cancel(self, job: Job) -> None:
        """Cancel a queued or running job (its worker is replaced if it was running)."""
        if job.done:
            return
        await self.executor.cancel(job.id)
        if not job.done:
            job.finish("cancelled", self.ttl)


def queue_full_problem(exc: QueueFullError) -> ProblemError:
    """503 with Retry-After."""
    return ProblemError("queue-full", str(exc), headers={"Retry-After": str(exc.retry_after)},
                        retry_after=exc.retry_after)
