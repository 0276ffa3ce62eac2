"""The local worker pool: :class:`ProcessExecutor`, the local :class:`Executor`.

``size`` long-lived worker processes (``forkserver`` or ``spawn``), each a
:class:`~service.backends.processes.WorkerProcess`. A task is sent to one idle worker;
progress messages and the result come back over its pipe. Because every worker is its own
process, a cancelled or timed-out task kills only its worker (which is replaced), and a
worker that dies (crash, OOM kill) fails only the task it was running. Admission is
bounded: at most ``size`` running plus ``queue_size`` waiting tasks, beyond that
:class:`QueueFullError` (the routes answer 503 with Retry-After).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from service.api.problems import failure_of
from service.api.task import TaskRequest
from service.backends.admission import retry_after
from service.backends.contracts import ProgressCallback, StartCallback, TaskHandle
from service.backends.errors import (
    ExecutorClosedError,
    QueueFullError,
    TaskCancelledError,
    TaskFailedError,
    WorkerDiedError,
)
from service.backends.loops import new_future, settle
from service.backends.processes import Message, WorkerProcess
from service.memory import free_deferred, release_between_tasks

logger = logging.getLogger("service.executor")


# ---------------------------------------------------------------------------- worker side


def _worker_main(conn: Connection, threads: int) -> None:
    """Entry point of a worker process: serve tasks from ``conn`` until it closes."""
    from service.worker import runtime

    runtime.start_worker_process(threads)
    from service import operations
    from service.api.problems import failure_of

    try:
        conn.send(("ready", os.getpid()))
    except OSError:  # the service stopped while this worker was starting
        return
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            break
        if message is None:
            break
        task_id, request = message

        def progress(stage: str, fraction: float, detail: dict[str, Any] | None = None,
                     _id: str = task_id) -> None:
            conn.send(("progress", _id, str(stage), float(fraction), detail))

        try:
            try:
                result = operations.run(request, progress)
                conn.send(("ok", task_id, result))
            except OSError:
                raise
            except Exception as exc:
                conn.send(("error", task_id, failure_of(exc)))
        except OSError:  # the pipe is gone: the service stopped
            break
        request = message = result = None  # drop the task's data before trimming the heap
        free_deferred()
        try:
            release_between_tasks(conn.poll)
        except (EOFError, OSError):
            break


# ------------------------------------------------------------------------------ main side


@dataclass
class _Task:
    id: str
    request: TaskRequest | None
    future: asyncio.Future[Any]
    progress_cb: ProgressCallback | None
    on_start: StartCallback | None
    submitted: float = field(default_factory=time.monotonic)
    started: float | None = None
    worker: _Worker | None = None


@dataclass
class _Worker:
    slot: int
    proc: WorkerProcess
    ready: bool = False
    task: _Task | None = None
    retiring: bool = False

    @property
    def pid(self) -> int | None:
        return self.proc.pid


class ProcessExecutor:
    """Local pool of worker processes (see the module docstring)."""

    def __init__(self, size: int, queue_size: int, *, start_method: str = "forkserver",
                 threads_per_worker: int = 1) -> None:
        self._size = size
        self._queue_size = queue_size
        self._start_method = start_method
        self._threads = threads_per_worker
        self._workers: dict[int, _Worker] = {}
        self._pending: collections.deque[_Task] = collections.deque()
        self._tasks: dict[str, _Task] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._started = False
        self._closing = False
        self._durations: collections.deque[float] = collections.deque(maxlen=50)
        self._start_failures: dict[int, int] = {}
        self._launches: set[asyncio.Task[None]] = set()
        self.restarts = 0
        self.deaths = 0

    # ----------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._started = True
        await asyncio.gather(*(self._launch(slot) for slot in range(self._size)))

    def begin_shutdown(self) -> None:
        """Stop replacing workers: from now on a worker that exits (e.g. killed to cancel a
        job while the service stops) stays gone. :meth:`shutdown` calls it first."""
        self._closing = True

    async def _launch(self, slot: int) -> None:
        proc = await asyncio.to_thread(WorkerProcess.spawn, _worker_main, self._threads,
                                       f"ffs-worker-{slot}", self._start_method)
        if self._closing:
            await asyncio.to_thread(proc.kill)
            return
        worker = _Worker(slot=slot, proc=proc)
        self._workers[slot] = worker
        proc.read(self._loop, lambda message: self._on_message(worker, message),
                  lambda: self._on_exit(worker), _unreadable, f"ffs-reader-{slot}")

    async def shutdown(self) -> None:
        """Fail the queued and running tasks, then end every worker: asked to stop, killed
        after 3 s, and a worker still being started is killed as soon as it exists."""
        self.begin_shutdown()
        while self._pending:
            task = self._pending.popleft()
            self._fail(task, ExecutorClosedError("the service is shutting down"))
        workers = list(self._workers.values())
        for worker in workers:
            if worker.task is not None:
                self._fail(worker.task, ExecutorClosedError("the service is shutting down"))
            with contextlib.suppress(Exception):
                worker.proc.conn.send(None)

        def stop() -> None:
            deadline = time.monotonic() + 3.0
            for worker in workers:
                worker.proc.process.join(max(0.0, deadline - time.monotonic()))
                worker.proc.kill()

        await asyncio.to_thread(stop)
        self._workers.clear()
        if self._launches:  # each kills its process once started (it sees _closing)
            await asyncio.gather(*self._launches, return_exceptions=True)

    # ---------------------------------------------------------------------- state

    def ready(self) -> bool:
        return self._started and not self._closing and self.workers_ready() > 0

    def size(self) -> int:
        return self._size

    def busy(self) -> int:
        return sum(1 for w in self._workers.values() if w.task is not None)

    def workers_ready(self) -> int:
        return sum(1 for w in self._workers.values() if w.ready and not w.retiring)

    def queue_depth(self) -> int:
        return len(self._pending)

    def worker_pids(self) -> list[int]:
        """Process ids of the current workers (for tests and diagnostics)."""
        return [w.pid for w in self._workers.values() if w.pid is not None]

    def running_pid(self, task_id: str) -> int | None:
        """Process id of the worker running ``task_id``, if it is running."""
        task = self._tasks.get(task_id)
        return task.worker.pid if task is not None and task.worker is not None else None

    def retry_after(self) -> int:
        """Seconds until a slot is likely free: mean task time x queue / workers."""
        return retry_after(self._durations, len(self._pending) + self.busy(), self._size)

    # --------------------------------------------------------------------- tasks

    async def submit(self, request: TaskRequest, *, progress_cb: ProgressCallback | None = None,
                     on_start: StartCallback | None = None,
                     task_id: str | None = None) -> TaskHandle:
        if not self._started or self._closing or self._loop is None:
            raise ExecutorClosedError("the worker pool is not running")
        if len(self._pending) + self.busy() >= self._size + self._queue_size:
            raise QueueFullError(self.retry_after())
        future = new_future()
        task = _Task(id=task_id or uuid.uuid4().hex, request=request, future=future,
                     progress_cb=progress_cb, on_start=on_start)
        self._tasks[task.id] = task
        future.add_done_callback(lambda _f, _id=task.id: self._tasks.pop(_id, None))
        self._pending.append(task)
        self._dispatch()
        return TaskHandle(task.id, future)

    async def cancel(self, task_id: str) -> bool:
        task = self._tasks.get(task_id)
        if task is None or task.future.done():
            return False
        worker = task.worker
        if worker is None:
            with contextlib.suppress(ValueError):
                self._pending.remove(task)
        else:
            # The only way to stop a running solve is to end its process; a new one replaces it.
            worker.retiring = True
            worker.task = None
            with contextlib.suppress(Exception):
                worker.proc.process.kill()
        self._fail(task, TaskCancelledError("cancelled"))
        return True

    def _fail(self, task: _Task, exc: BaseException) -> None:
        task.request = None
        settle(task.future, exc=exc)

    def _dispatch(self) -> None:
        for worker in list(self._workers.values()):
            if not self._pending:
                return
            if not worker.ready or worker.retiring or worker.task is not None:
                continue
            task = self._pending.popleft()
            worker.task, task.worker, task.started = task, worker, time.monotonic()
            try:
                worker.proc.conn.send((task.id, task.request))
            except OSError:  # the worker died before taking the task: give it to another
                worker.task, task.worker, task.started = None, None, None
                worker.retiring = True
                self._pending.appendleft(task)
                continue
            except Exception as exc:  # e.g. an unpicklable request
                logger.error("could not send task %s to a worker", task.id)
                worker.task, task.worker = None, None
                self._fail(task, TaskFailedError(failure_of(exc)))  # logs its traceback
                continue
            task.request = None
            if task.on_start is not None:
                _safe_call(task.on_start)

    # ----------------------------------------------------------- reader callbacks

    def _on_message(self, worker: _Worker, message: Message) -> None:
        kind = message[0]
        if kind == "ready":
            worker.ready = True
            self._dispatch()
            return
        task = worker.task
        if task is None or (message[1] is not None and message[1] != task.id):
            return  # a late message of a cancelled task
        if kind == "progress":
            if task.progress_cb is not None:
                detail = message[4] if len(message) > 4 else None
                _safe_call(task.progress_cb, message[2], message[3],
                           *(() if detail is None else (detail,)))
            return
        worker.task, task.worker = None, None
        if task.started is not None:
            self._durations.append(time.monotonic() - task.started)
        if kind == "ok":
            settle(task.future, result=message[2])
        else:
            self._fail(task, TaskFailedError(message[2]))
        self._dispatch()

    def _on_exit(self, worker: _Worker) -> None:
        if self._workers.get(worker.slot) is worker:
            del self._workers[worker.slot]
        if self._closing:
            return
        task = worker.task
        if task is not None:
            self.deaths += 1
            reason = (f"the worker process running this task died "
                      f"({worker.proc.exit_reason()}); the input may be too large for the "
                      "memory available")
            logger.error("task %s (%s): worker %s: %s", task.id,
                         task.request and task.request.task_name, worker.pid, reason)
            worker.task, task.worker = None, None
            self._fail(task, WorkerDiedError(reason))
        elif not worker.retiring:
            logger.warning("idle worker %s exited (%s)", worker.pid, worker.proc.exit_reason())
        self.restarts += 1
        delay = 0.0
        if worker.ready:
            self._start_failures.pop(worker.slot, None)
        else:  # it died while starting: back off instead of respawning in a tight loop
            failures = self._start_failures.get(worker.slot, 0) + 1
            self._start_failures[worker.slot] = failures
            delay = min(30.0, 0.25 * 2 ** (failures - 1))
            logger.error("worker slot %s failed to start (%s times, %s); retrying in %.2f s",
                         worker.slot, failures, worker.proc.exit_reason(), delay)
        assert self._loop is not None
        launch = self._loop.create_task(self._relaunch(worker.slot, delay))
        self._launches.add(launch)
        launch.add_done_callback(self._launches.discard)

    async def _relaunch(self, slot: int, delay: float = 0.0) -> None:
        try:
            if delay:
                await asyncio.sleep(delay)
            if self._closing:
                return
            await self._launch(slot)
        except Exception:
            logger.exception("could not restart worker slot %s", slot)


def _unreadable(exc: Exception) -> Message:
    logger.error("unreadable worker message")
    return ("error", None, failure_of(exc))


def _safe_call(fn: Callable[..., None], *args: Any) -> None:
    try:
        fn(*args)
    except Exception:
        logger.exception("executor callback failed")
