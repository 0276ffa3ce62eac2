"""Local jobs: records in this process's memory (:class:`MemoryJobStore`), run on the
local executor by :class:`JobManager` (the local :class:`~service.backends.contracts.JobService`).

A job runs one task on the executor. Its record (:class:`~service.backends.jobs.Job`) holds
the state, per-stage progress and timings, the failure, and the result (the encoded body
plus the mesh arrays, so that ``GET /v1/jobs/{id}/result`` can return glTF or add
colours). Finished jobs expire ``FFS_JOB_TTL`` seconds after they finish; a sweeper removes
them.

Jobs live only in this process: when the service stops, queued and running jobs are
cancelled (their workers ended) and every record is dropped. A job id begins with the
millisecond its service started (:func:`new_job_id`), so after a restart an id from before
it is answered :class:`JobLostError` (410) rather than "not found".
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import uuid
from typing import Any, Protocol

from service.api.problems import failure
from service.api.task import TaskRequest, TaskResult
from service.backends.contracts import Executor, JobPolicy, ResultCallback
from service.backends.errors import (
    ClientJobsError,
    ExecutorClosedError,
    JobLostError,
    JobStoreFullError,
    TaskCancelledError,
    TaskFailedError,
    WorkerDiedError,
)
from service.backends.jobs import Job, admit, count_states
from service.backends.loops import sweep_forever

logger = logging.getLogger("service.jobs")


class JobStore(Protocol):
    """Where jobs live. The in-memory store is per process; a shared one could replace it."""

    def add(self, job: Job) -> None: ...

    def get(self, job_id: str) -> Job | None: ...

    def remove(self, job_id: str) -> None: ...

    def jobs(self) -> list[Job]:
        """Every stored job."""

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

    def jobs(self) -> list[Job]:
        return list(self._jobs.values())

    def expired(self, now: float) -> list[str]:
        return [j.id for j in self._jobs.values()
                if j.expires_at is not None and j.expires_at <= now]

    def __len__(self) -> int:
        return len(self._jobs)

    def counts(self) -> dict[str, int]:
        return count_states(self._jobs.values())


_ID_TIME = 12
"""Hex digits of a job id that hold its service's start time (milliseconds since 1970)."""


def new_job_id(started_ms: int) -> str:
    """A 32-hex-digit job id: the service's start time, then 80 random bits."""
    return f"{started_ms:0{_ID_TIME}x}{uuid.uuid4().hex[:32 - _ID_TIME]}"


def started_before(job_id: str, started_ms: int) -> bool:
    """Whether ``job_id`` has this module's shape and comes from a service started before
    ``started_ms`` (a plausible time: after 2024)."""
    if len(job_id) != 32:
        return False
    try:
        stamp = int(job_id[:_ID_TIME], 16)
    except ValueError:
        return False
    return _EPOCH_2024_MS <= stamp < started_ms


_EPOCH_2024_MS = 1_704_067_200_000


def _iso_ms(ms: int) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(ms / 1000)) + f".{ms % 1000:03d}Z"


class JobManager:
    """Runs jobs on the executor and keeps their records in a :class:`JobStore`."""

    def __init__(self, store: JobStore, executor: Executor, policy: JobPolicy,
                 on_result: ResultCallback | None = None) -> None:
        self.store, self.executor, self.policy = store, executor, policy
        self.on_result = on_result
        self._runners: dict[str, asyncio.Task[None]] = {}
        self._sweeper: asyncio.Task[None] | None = None
        self.started_ms = int(time.time() * 1000)

    async def start(self) -> None:
        self._sweeper = asyncio.create_task(
            sweep_forever(self.policy.ttl, self._expire_async, "job sweeper", ceiling=30.0))

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

    async def _expire_async(self) -> None:
        self.expire()

    async def submit(self, request: TaskRequest, *, color: str | None = None,
                     owner: str | None = None, max_per_owner: int | None = None) -> Job:
        """Create a job and queue it; the oldest finished jobs give way when the store is
        full (``JobStoreFullError``, ``ClientJobsError``, ``QueueFullError``,
        ``ExecutorClosedError``)."""
        self.expire()
        per_owner = max_per_owner or self.policy.max_per_client
        evict, refusal = admit(self.store.jobs(), self.policy.max_jobs, owner, per_owner)
        if refusal == "owner":
            raise ClientJobsError(per_owner)
        if refusal == "full":
            raise JobStoreFullError(len(self.store), self.policy.max_jobs)
        job = Job(id=new_job_id(self.started_ms), operation=request.operation, color=color,
                  owner=owner)
        handle = await self.executor.submit(request, task_id=job.id,
                                            progress_cb=job.update_progress,
                                            on_start=job.mark_running)
        for job_id in evict:
            self.store.remove(job_id)
        self.store.add(job)
        self._runners[job.id] = asyncio.create_task(self._run(job, handle.future))
        return job

    async def _run(self, job: Job, future: asyncio.Future[Any]) -> None:
        try:
            result = await asyncio.wait_for(asyncio.shield(future), self.policy.timeout)
        except TimeoutError:
            await self.executor.cancel(job.id)
            self._fail(job, failure("timeout", f"the job did not finish within "
                                               f"{self.policy.timeout:g} s (FFS_JOB_TIMEOUT)"))
        except TaskCancelledError:
            if not job.done:
                job.finish("cancelled", self.policy.ttl)
        except TaskFailedError as exc:
            self._fail(job, exc.error)
        except WorkerDiedError as exc:
            self._fail(job, failure("worker-died", exc.reason))
        except ExecutorClosedError as exc:
            self._fail(job, failure("unavailable", str(exc)))
        except asyncio.CancelledError:
            await self.executor.cancel(job.id)
            if not job.done:
                job.finish("cancelled", self.policy.ttl)
            raise
        else:
            if not job.done:
                job.result = result
                job.finish("succeeded", self.policy.ttl)
                if self.on_result is not None:
                    self.on_result(job.operation, result)
        finally:
            self._runners.pop(job.id, None)

    async def get(self, job_id: str) -> Job | None:
        """The job, ``None`` if there is none (expired, deleted, never existed), or
        :class:`JobLostError` for an id from before this service started."""
        job = self.store.get(job_id)
        if job is None and started_before(job_id, self.started_ms):
            raise JobLostError(job_id, _iso_ms(self.started_ms))
        return job

    async def list(self, owner: str | None = None) -> list[Job]:
        self.expire()
        return sorted((j for j in self.store.jobs() if owner is None or j.owner == owner),
                      key=lambda j: j.created_at)

    async def result(self, job: Job) -> TaskResult:
        assert job.result is not None, "only a succeeded job is asked for its result"
        return job.result

    async def delete(self, job: Job) -> None:
        self.store.remove(job.id)

    def counts(self) -> dict[str, int]:
        return self.store.counts()

    def _fail(self, job: Job, error: dict[str, Any]) -> None:
        if job.done:
            return
        job.error = error
        job.finish("failed", self.policy.ttl)

    async def cancel(self, job: Job) -> None:
        """Cancel a queued or running job (its worker is replaced if it was running)."""
        if job.done:
            return
        await self.executor.cancel(job.id)
        if not job.done:
            job.finish("cancelled", self.policy.ttl)
