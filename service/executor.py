"""The worker pool: solver work never runs on the event loop.

Routes and the job manager talk to an :class:`Executor` only::

    handle = await executor.submit("reconstruct", payload, progress_cb=cb)  # QueueFullError
    result = await handle.future            # TaskFailedError, WorkerDiedError, TaskCancelledError
    await executor.cancel(handle.id)

:class:`ProcessExecutor` is the local implementation: ``size`` long-lived worker processes
(``forkserver`` or ``spawn``), each with its own duplex pipe and a reader thread in the main
process. A task is sent to one idle worker; progress messages and the result come back over
its pipe. Because every worker is its own process, a cancelled or timed-out task kills only
its worker (which is replaced), and a worker that dies (crash, OOM kill) fails only the task
it was running. Admission is bounded: at most ``size`` running plus ``queue_size`` waiting
tasks, beyond that :class:`QueueFullError` (the routes answer 503 with Retry-After).

:class:`service.cluster.DaskExecutor` implements the same protocol on a Dask cluster
(``FFS_EXECUTOR=dask``): ``submit`` returns a :class:`TaskHandle` whose ``future`` resolves
on the event loop.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import multiprocessing
import os
import signal
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Protocol

logger = logging.getLogger("service.executor")

ProgressCallback = Callable[[str, float], None]
StartCallback = Callable[[], None]


def post_threadsafe(loop: asyncio.AbstractEventLoop | None, fn: Callable[..., None],
                    *args: Any) -> bool:
    """Schedule ``fn(*args)`` on ``loop`` from a reader thread; False once the loop is gone."""
    if loop is None or loop.is_closed():
        return False
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:
        return False
    return True


class ExecutorError(Exception):
    """Base class of executor failures."""


class QueueFullError(ExecutorError):
    """No capacity: ``size`` tasks running and ``queue_size`` waiting."""

    def __init__(self, retry_after: int) -> None:
        super().__init__(f"the work queue is full; retry after {retry_after} s")
        self.retry_after = retry_after


class ExecutorClosedError(ExecutorError):
    """The executor is not running (not started yet, or shutting down)."""


class TaskCancelledError(ExecutorError):
    """The task was cancelled before it finished."""


class WorkerDiedError(ExecutorError):
    """The worker process running the task exited; ``reason`` says how."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class TaskFailedError(ExecutorError):
    """The task raised; ``error`` is the dict made by :func:`service.tasks.describe_error`."""

    def __init__(self, error: dict[str, Any]) -> None:
        super().__init__(str(error.get("message") or error.get("detail") or error))
        self.error = error


@dataclass
class TaskHandle:
    """A submitted task: its id and an asyncio future of its result."""

    id: str
    future: asyncio.Future[Any]


class Executor(Protocol):
    """What the routes need from a worker pool (local processes now, Dask later)."""

    async def start(self) -> None:
        """Start the workers (called once from the app's lifespan)."""

    async def submit(self, fn_name: str, payload: dict[str, Any], *,
                     progress_cb: ProgressCallback | None = None,
                     on_start: StartCallback | None = None,
                     task_id: str | None = None) -> TaskHandle:
        """Queue ``service.tasks.TASKS[fn_name](payload, progress)``; raise
        :class:`QueueFullError` at once when there is no room. ``progress_cb(stage, fraction)``
        and ``on_start()`` are called on the event loop."""

    async def cancel(self, task_id: str) -> bool:
        """Cancel a queued or running task; True if it was still pending."""

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

    async def shutdown(self) -> None:
        """Stop the workers; pending tasks fail with :class:`ExecutorClosedError`."""


# ---------------------------------------------------------------------------- worker side


def prepare_worker_process(threads: int) -> None:
    """First thing in a worker or session process, before numpy or MKL load: cap their
    threads (MKL reads the variables only at load time) and leave Ctrl-C to the parent,
    which shuts the process down."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _worker_main(conn: Connection, threads: int) -> None:
    """Entry point of a worker process: serve tasks from ``conn`` until it closes."""
    prepare_worker_process(threads)
    from service import tasks

    tasks.initialize_worker(threads)
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
        task_id, fn_name, payload = message

        def progress(stage: str, fraction: float, _id: str = task_id) -> None:
            conn.send(("progress", _id, str(stage), float(fraction)))

        try:
            try:
                result = tasks.run(fn_name, payload, progress)
                conn.send(("ok", task_id, result))
            except OSError:
                raise
            except Exception as exc:
                conn.send(("error", task_id, tasks.describe_error(exc)))
        except OSError:  # the pipe is gone: the service stopped
            break
        payload = message = result = None  # drop the task's data before trimming the heap
        tasks.release_memory()


# ------------------------------------------------------------------------------ main side


@dataclass
class _Task:
    id: str
    fn_name: str
    payload: dict[str, Any] | None
    future: asyncio.Future[Any]
    progress_cb: ProgressCallback | None
    on_start: StartCallback | None
    submitted: float = field(default_factory=time.monotonic)
    started: float | None = None
    worker: _Worker | None = None


@dataclass
class _Worker:
    slot: int
    process: Any
    conn: Connection
    ready: bool = False
    task: _Task | None = None
    retiring: bool = False
    pid: int | None = None


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
        self.restarts = 0
        self.deaths = 0

    # ----------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._started = True
        await asyncio.gather(*(self._launch(slot) for slot in range(self._size)))

    def _context(self) -> Any:
        ctx = multiprocessing.get_context(self._start_method)
        if self._start_method == "forkserver":
            ctx.set_forkserver_preload(["service.tasks"])
        return ctx

    def _make_worker(self, slot: int) -> _Worker:
        """Start one worker process (blocking; runs in a thread)."""
        ctx = self._context()
        parent, child = ctx.Pipe(duplex=True)
        process = ctx.Process(target=_worker_main, args=(child, self._threads),
                              name=f"ffs-worker-{slot}", daemon=True)
        process.start()
        child.close()
        return _Worker(slot=slot, process=process, conn=parent, pid=process.pid)

    async def _launch(self, slot: int) -> None:
        worker = await asyncio.to_thread(self._make_worker, slot)
        if self._closing:
            with contextlib.suppress(Exception):
                worker.process.kill()
            return
        self._workers[slot] = worker
        threading.Thread(target=self._reader, args=(worker,), daemon=True,
                         name=f"ffs-reader-{slot}").start()

    async def shutdown(self) -> None:
        self._closing = True
        while self._pending:
            task = self._pending.popleft()
            self._fail(task, ExecutorClosedError("the service is shutting down"))
        workers = list(self._workers.values())
        for worker in workers:
            if worker.task is not None:
                self._fail(worker.task, ExecutorClosedError("the service is shutting down"))
            with contextlib.suppress(Exception):
                worker.conn.send(None)

        def stop() -> None:
            deadline = time.monotonic() + 3.0
            for worker in workers:
                worker.process.join(max(0.0, deadline - time.monotonic()))
                if worker.process.is_alive():
                    worker.process.kill()
                    worker.process.join(1.0)
                with contextlib.suppress(Exception):
                    worker.conn.close()

        await asyncio.to_thread(stop)
        self._workers.clear()

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
        mean = (sum(self._durations) / len(self._durations)) if self._durations else 1.0
        waiting = len(self._pending) + self.busy()
        return max(1, min(120, math.ceil(mean * waiting / max(1, self._size))))

    # --------------------------------------------------------------------- tasks

    async def submit(self, fn_name: str, payload: dict[str, Any], *,
                     progress_cb: ProgressCallback | None = None,
                     on_start: StartCallback | None = None,
                     task_id: str | None = None) -> TaskHandle:
        if not self._started or self._closing or self._loop is None:
            raise ExecutorClosedError("the worker pool is not running")
        if len(self._pending) + self.busy() >= self._size + self._queue_size:
            raise QueueFullError(self.retry_after())
        future: asyncio.Future[Any] = self._loop.create_future()
        future.add_done_callback(_consume_exception)
        task = _Task(id=task_id or uuid.uuid4().hex, fn_name=fn_name, payload=payload,
                     future=future, progress_cb=progress_cb, on_start=on_start)
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
                worker.process.kill()
        self._fail(task, TaskCancelledError("cancelled"))
        return True

    def _fail(self, task: _Task, exc: BaseException) -> None:
        task.payload = None
        if not task.future.done():
            task.future.set_exception(exc)

    def _dispatch(self) -> None:
        for worker in list(self._workers.values()):
            if not self._pending:
                return
            if not worker.ready or worker.retiring or worker.task is not None:
                continue
            task = self._pending.popleft()
            worker.task, task.worker, task.started = task, worker, time.monotonic()
            try:
                worker.conn.send((task.id, task.fn_name, task.payload))
            except OSError:  # the worker died before taking the task: give it to another
                worker.task, task.worker, task.started = None, None, None
                worker.retiring = True
                self._pending.appendleft(task)
                continue
            except Exception as exc:  # e.g. an unpicklable payload
                worker.task, task.worker = None, None
                self._fail(task, TaskFailedError({
                    "category": "internal", "exception": type(exc).__name__,
                    "message": f"could not send the task to a worker: {exc}"}))
                continue
            task.payload = None
            if task.on_start is not None:
                _safe_call(task.on_start)

    # ----------------------------------------------------------- reader callbacks

    def _reader(self, worker: _Worker) -> None:
        """Thread: forward every message of one worker to the event loop."""
        while True:
            try:
                message = worker.conn.recv()
            except (EOFError, OSError):
                break
            except Exception as exc:  # a result that cannot be unpickled
                message = ("error", None, {"category": "internal",
                                           "exception": type(exc).__name__,
                                           "message": f"unreadable worker message: {exc}"})
            if not self._post(self._on_message, worker, message):
                return
        worker.process.join(5.0)
        self._post(self._on_exit, worker)

    def _post(self, fn: Callable[..., None], *args: Any) -> bool:
        return post_threadsafe(self._loop, fn, *args)

    def _on_message(self, worker: _Worker, message: tuple[Any, ...]) -> None:
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
                _safe_call(task.progress_cb, message[2], message[3])
            return
        worker.task, task.worker = None, None
        if task.started is not None:
            self._durations.append(time.monotonic() - task.started)
        if kind == "ok":
            if not task.future.done():
                task.future.set_result(message[2])
        else:
            self._fail(task, TaskFailedError(message[2]))
        self._dispatch()

    def _on_exit(self, worker: _Worker) -> None:
        if self._workers.get(worker.slot) is worker:
            del self._workers[worker.slot]
        if self._closing:
            return
        code = worker.process.exitcode
        task = worker.task
        if task is not None:
            self.deaths += 1
            how = (f"killed by signal {signal.Signals(-code).name}" if code is not None
                   and code < 0 and -code in signal.Signals._value2member_map_
                   else f"exit code {code}")
            reason = (f"the worker process (pid {worker.pid}) running this task died ({how}); "
                      "the input may be too large for the memory available")
            logger.error("task %s (%s): %s", task.id, task.fn_name, reason)
            worker.task, task.worker = None, None
            self._fail(task, WorkerDiedError(reason))
        elif not worker.retiring:
            logger.warning("idle worker %s exited with code %s", worker.pid, code)
        self.restarts += 1
        delay = 0.0
        if worker.ready:
            self._start_failures.pop(worker.slot, None)
        else:  # it died while starting: back off instead of respawning in a tight loop
            failures = self._start_failures.get(worker.slot, 0) + 1
            self._start_failures[worker.slot] = failures
            delay = min(30.0, 0.25 * 2 ** (failures - 1))
            logger.error("worker slot %s failed to start (%s times, exit code %s); retrying "
                         "in %.2f s", worker.slot, failures, code, delay)
        assert self._loop is not None
        self._loop.create_task(self._relaunch(worker.slot, delay))

    async def _relaunch(self, slot: int, delay: float = 0.0) -> None:
        try:
            if delay:
                await asyncio.sleep(delay)
            if self._closing:
                return
            await self._launch(slot)
        except Exception:
            logger.exception("could not restart worker slot %s", slot)


def _safe_call(fn: Callable[..., None], *args: Any) -> None:
    try:
        fn(*args)
    except Exception:
        logger.exception("executor callback failed")


def _consume_exception(future: asyncio.Future[Any]) -> None:
    """Mark a future's exception as retrieved (nobody may await a cancelled job)."""
    if not future.cancelled():
        future.exception()


def make_executor(settings: Any) -> Executor:
    """The local executor (``settings.executor`` ``local``; Dask: service.cluster)."""
    if settings.executor in ("local", "process"):
        return ProcessExecutor(settings.workers, settings.queue_size,
                               start_method=settings.start_method,
                               threads_per_worker=settings.effective_threads)
    raise ValueError(f"unknown executor {settings.executor!r}")
