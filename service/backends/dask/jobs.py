"""Jobs on a Dask cluster: :class:`DaskJobManager`.

A job's record lives in the scheduler (:class:`~service.backends.dask.registry.Registry`),
so any replica answers for it. The result stays in the worker's memory, held by a
published dataset ``ffs-job-{id}`` so that any replica can fetch it; it is unpublished when
the job expires (``FFS_JOB_TTL``) or is deleted.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
import uuid
from typing import Any

from service.api.problems import failure
from service.api.task import TaskRequest, TaskResult
from service.backends.contracts import JobPolicy, ResultCallback
from service.backends.dask.executor import DaskExecutor
from service.backends.dask.registry import JOB_PREFIX
from service.backends.errors import (
    ClientJobsError,
    ExecutorClosedError,
    JobStoreFullError,
    TaskFailedError,
)
from service.backends.jobs import FIELDS, STATES, Job, job_fields
from service.backends.loops import sweep_forever


class DaskJobManager:
    """The :class:`~service.backends.contracts.JobService` with the job state in the
    scheduler's :class:`~service.backends.dask.registry.Registry`."""

    def __init__(self, executor: DaskExecutor, policy: JobPolicy,
                 on_result: ResultCallback | None = None) -> None:
        self.executor, self.connection, self.policy = executor, executor.connection, policy
        self.on_result = on_result
        self._counts: dict[str, int] = dict.fromkeys(STATES, 0)
        self._watchers: set[asyncio.Task[None]] = set()
        self._sweeper: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._sweeper = asyncio.create_task(sweep_forever(
            self.policy.ttl, self.sweep, "job sweeper", active=self.connection.connected_now))

    async def stop(self) -> None:
        for task in (self._sweeper, *self._watchers):
            if task is not None:
                task.cancel()
        for task in (self._sweeper, *self._watchers):
            if task is not None:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task

    def counts(self) -> dict[str, int]:
        return dict(self._counts)

    async def sweep(self) -> None:
        """Expire and time out jobs in the registry; drop their results from the cluster."""
        swept = await self.connection.call("job_sweep", time.time())
        self._counts = swept["counts"]
        client = self.connection.client
        for job_id in swept["timed_out"]:
            future = await client.get_dataset(JOB_PREFIX + job_id, default=None)
            if future is not None:
                with contextlib.suppress(Exception):
                    await client.cancel([future], force=True)
        for job_id in swept["expired"]:
            with contextlib.suppress(KeyError, Exception):
                await client.unpublish_dataset(JOB_PREFIX + job_id)

    async def submit(self, request: TaskRequest, *, color: str | None = None,
                     owner: str | None = None, max_per_owner: int | None = None) -> Job:
        client = await self.connection.wait_connected(5.0)
        job = Job(id=uuid.uuid4().hex, operation=request.operation, color=color, owner=owner)
        meta = {"key": JOB_PREFIX + job.id, "ttl": self.policy.ttl, "timeout": self.policy.timeout}
        refusal = await self.connection.call("job_add", job_fields(job), meta,
                                             self.policy.max_jobs, time.time(),
                                             max_per_owner or self.policy.max_per_client)
        if refusal == "owner":
            raise ClientJobsError(max_per_owner or self.policy.max_per_client)
        if refusal is not None:
            raise JobStoreFullError(int(refusal), self.policy.max_jobs)
        try:
            handle = await self.executor.submit(request, task_id=job.id, job=True)
            if not await self.connection.call_async("wait_for_key", meta["key"], 30.0):
                raise ExecutorClosedError("the Dask scheduler did not receive the job")
            await client.publish_dataset(self.executor.dask_future(job.id),
                                         name=JOB_PREFIX + job.id)
        except BaseException:
            with contextlib.suppress(Exception):
                await self.connection.call("job_remove", job.id)
            raise
        watcher = asyncio.create_task(self._watch(job, handle.future))
        self._watchers.add(watcher)
        watcher.add_done_callback(self._watchers.discard)
        return job

    async def _watch(self, job: Job, future: asyncio.Future[Any]) -> None:
        """Metrics for jobs this replica submitted (their state is the registry's)."""
        with contextlib.suppress(Exception):
            result = await asyncio.wait_for(asyncio.shield(future), self.policy.timeout)
            if self.on_result is not None:
                self.on_result(job.operation, result)

    async def get(self, job_id: str) -> Job | None:
        record = await self.connection.call("job_get", job_id, time.time())
        return None if record is None else Job(**record)

    async def list(self, owner: str | None = None) -> list[Job]:
        records = await self.connection.call("job_list", owner, time.time())
        return [Job(**record) for record in records]

    async def result(self, job: Job) -> TaskResult:
        client = self.connection.require()
        future = await client.get_dataset(JOB_PREFIX + job.id, default=None)
        if future is None:
            raise TaskFailedError(failure("not-found", f"the result of job {job.id} is gone "
                                                       "(it expired)"))
        try:
            value = await asyncio.wait_for(future, 60)
        except Exception as exc:
            raise TaskFailedError(failure(
                "job-failed", f"job {job.id}: its result could not be fetched from the "
                              f"cluster ({type(exc).__name__}: {exc})")) from None
        if not value.get("ok"):
            raise TaskFailedError(value["error"])
        result: TaskResult = value["result"]
        return result

    async def cancel(self, job: Job) -> None:
        record = await self.connection.call("job_finish", job.id, "cancelled", None,
                                            time.time())
        if record is not None:
            for name in FIELDS:
                setattr(job, name, record[name])
        if not await self.executor.cancel(job.id):
            client = self.connection.require()
            future = await client.get_dataset(JOB_PREFIX + job.id, default=None)
            if future is not None:
                with contextlib.suppress(Exception):
                    await client.cancel([future], force=True)

    async def delete(self, job: Job) -> None:
        await self.connection.call("job_remove", job.id)
        with contextlib.suppress(KeyError, Exception):
            await self.connection.require().unpublish_dataset(JOB_PREFIX + job.id)
