"""The :class:`~service.backends.contracts.Executor` on a Dask cluster: :class:`DaskExecutor`.

Tasks (synchronous requests and jobs) run :func:`~service.backends.dask.worker.run_task` on
the workers through ``client.submit(..., pure=False, retries=1)``: a worker that dies
mid-task makes the scheduler run the task again elsewhere, up to
``distributed.scheduler.allowed-failures`` times (1 in docker-compose.yml and the tests),
after which the task fails with ``KilledWorker`` and reports ``worker-died``.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
import uuid
from typing import Any

from service.api.problems import failure_of
from service.api.task import TaskRequest
from service.backends.admission import retry_after
from service.backends.contracts import TaskHandle
from service.backends.dask.connection import DaskConnection
from service.backends.dask.registry import JOB_PREFIX
from service.backends.dask.worker import run_task
from service.backends.errors import (
    ExecutorClosedError,
    QueueFullError,
    TaskCancelledError,
    TaskFailedError,
    WorkerDiedError,
)
from service.backends.loops import new_future, settle


class DaskExecutor:
    """The :class:`~service.backends.contracts.Executor` protocol on a Dask cluster.

    Admission is per replica: at most (cluster threads + ``queue_size``) tasks of this
    replica in flight, beyond that :class:`QueueFullError`. ``progress_cb`` is not
    used: job progress travels through the scheduler (:class:`Registry`). A cancelled or
    timed-out task is cancelled on the cluster; a task already running finishes in its
    worker thread (Dask cannot interrupt it) and its result is dropped.
    """

    def __init__(self, connection: DaskConnection, queue_size: int, threads: int = 1) -> None:
        self.connection = connection
        self._queue_size = queue_size
        self._threads = threads
        self._futures: dict[str, Any] = {}
        self._handles: dict[str, asyncio.Future[Any]] = {}
        self._watchers: set[asyncio.Task[None]] = set()
        self._started = False
        self._closing = False
        self._durations: list[float] = []
        self.restarts = 0

    async def start(self) -> None:
        self._started = True
        await self.connection.start()

    def begin_shutdown(self) -> None:
        """Nothing to stop replacing here: the cluster manages its own workers."""

    async def shutdown(self) -> None:
        self._closing = True
        for handle in self._handles.values():
            if not handle.done():
                handle.set_exception(ExecutorClosedError("the service is shutting down"))
        for watcher in list(self._watchers):
            watcher.cancel()
        await self.connection.close()

    def ready(self) -> bool:
        return (self._started and not self._closing and self.connection.client is not None
                and self.connection.workers > 0)

    def size(self) -> int:
        return self.connection.threads

    def workers_ready(self) -> int:
        return self.connection.workers

    def busy(self) -> int:
        return min(len(self._futures), self.size())

    def queue_depth(self) -> int:
        return max(0, len(self._futures) - self.size())

    def retry_after(self) -> int:
        return retry_after(self._durations, len(self._futures), self.size())

    def dask_future(self, task_id: str) -> Any:
        return self._futures.get(task_id)

    async def submit(self, request: TaskRequest, *, progress_cb: Any = None,
                     on_start: Any = None, task_id: str | None = None,
                     job: bool = False) -> TaskHandle:
        if not self._started or self._closing:
            raise ExecutorClosedError("the worker pool is not running")
        client = self.connection.require()
        if len(self._futures) >= self.size() + self._queue_size:
            raise QueueFullError(self.retry_after())
        task_id = task_id or uuid.uuid4().hex
        key = f"{JOB_PREFIX}{task_id}" if job else f"ffs-task-{request.task_name}-{task_id}"
        future = client.submit(run_task, request, task_id if job else None, self._threads,
                               key=key, pure=False, retries=1)
        handle = new_future()
        self._futures[task_id] = future
        self._handles[task_id] = handle
        watcher = asyncio.create_task(self._watch(task_id, future, handle))
        self._watchers.add(watcher)
        watcher.add_done_callback(self._watchers.discard)
        return TaskHandle(task_id, handle)

    async def _watch(self, task_id: str, future: Any, handle: asyncio.Future[Any]) -> None:
        from distributed.client import FutureCancelledError

        start = time.monotonic()
        try:
            value = await future
        except FutureCancelledError as exc:
            settle(handle, exc=TaskCancelledError(f"cancelled ({exc.reason})"))
        except asyncio.CancelledError:
            settle(handle, exc=ExecutorClosedError("the service is shutting down"))
            raise
        except Exception as exc:
            if type(exc).__name__ == "KilledWorker":
                settle(handle, exc=WorkerDiedError(
                    f"the Dask workers running this task died {exc.args[2] + 1} times "
                    f"({exc}); the input may be too large for a worker's memory"))
            elif isinstance(exc, OSError):
                settle(handle, exc=ExecutorClosedError(f"lost the Dask scheduler: {exc}"))
            else:
                settle(handle, exc=TaskFailedError(failure_of(exc)))  # logged there
        else:
            self._durations = [*self._durations[-49:], time.monotonic() - start]
            if value.get("ok"):
                settle(handle, result=value["result"])
            else:
                settle(handle, exc=TaskFailedError(value["error"]))
        finally:
            self._futures.pop(task_id, None)
            self._handles.pop(task_id, None)

    async def cancel(self, task_id: str) -> bool:
        future = self._futures.get(task_id)
        handle = self._handles.get(task_id)
        if future is None or handle is None or handle.done():
            return False
        client = self.connection.client
        if client is not None:
            with contextlib.suppress(Exception):
                await client.cancel([future], force=True)
        settle(handle, exc=TaskCancelledError("cancelled"))
        return True
