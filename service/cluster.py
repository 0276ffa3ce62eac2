"""The Dask distributed backend (``FFS_EXECUTOR=dask``): executor, jobs and sessions.

Work and state live on an existing Dask cluster, so any number of service replicas can
share it (design and measurements: docs/distributed.md):

* **Tasks** (synchronous requests and jobs) run :func:`run_task` on the workers through
  ``client.submit(..., pure=False, retries=1)``. Failures come back as values (the same
  error dicts as the local pool), so Dask retries only what dies with its worker: a worker
  that dies mid-task makes the scheduler run the task again elsewhere, up to
  ``distributed.scheduler.allowed-failures`` times (1 in docker-compose.yml and the tests:
  one retry), after which the task fails with ``KilledWorker`` and the job reports
  ``worker-died`` with that reason.
* **Job state** lives in the scheduler, in :class:`Registry`: a scheduler plugin that keeps
  the job records and follows their tasks' transitions (queued -> running -> succeeded /
  failed / cancelled) itself, so a job does not depend on the replica that submitted it.
  Workers send progress as scheduler events (``Worker.log_event``, batched, non-blocking);
  the plugin folds them into the record. The result stays in the worker's memory, held by
  a published dataset ``ffs-job-{id}`` so that any replica can fetch it; it is unpublished
  when the job expires (``FFS_JOB_TTL``) or is deleted.
* **Sessions** are Dask actors (:class:`SessionActor`, one :class:`SessionState` each)
  pinned to the worker that built them, held by a published dataset
  ``ffs-session-{id}``. The registry admits them against FFS_MAX_SESSIONS and
  FFS_MAX_SESSION_MEMORY atomically, tracks their last use, expires idle ones and buries
  the sessions of a worker that leaves the cluster (410 afterwards).

Replicas reach the registry with ``Client.run_on_scheduler``; the first call installs the
plugin in the scheduler (or ``dask scheduler --preload service.cluster`` does at start).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import os
import pickle
import time
import uuid
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from service.executor import (
    ExecutorClosedError,
    QueueFullError,
    TaskCancelledError,
    TaskFailedError,
    TaskHandle,
    WorkerDiedError,
)
from service.jobs import Job, queue_full_problem
from service.problems import ProblemError, from_worker_error
from service.sessions import (
    estimate_memory,
    gone_problem,
    memory_problem,
    not_found,
    session_document,
    too_many,
)

logger = logging.getLogger("service.cluster")


async def sweep_forever(connection: Any, ttl: float, sweep: Callable[[], Awaitable[Any]],
                        what: str) -> None:
    """Call ``sweep()`` every ttl / 4 (0.05 to 5 s) while connected; log, never stop."""
    interval = max(0.05, min(5.0, ttl / 4))
    while True:
        await asyncio.sleep(interval)
        if connection.client is None:
            continue
        try:
            await sweep()
        except Exception:
            logger.exception("%s failed", what)


REGISTRY_NAME = "ffs-registry"
PROGRESS_TOPIC = "ffs-job"
JOB_PREFIX = "ffs-job-"
SESSION_PREFIX = "ffs-session-"
_JOB_FIELDS = tuple(f.name for f in dataclasses.fields(Job) if f.name != "result")

try:  # the plugin base class; without dask the module still imports (for docs/tests)
    from distributed.diagnostics.plugin import SchedulerPlugin
except ImportError:  # pragma: no cover - dask is an optional extra
    SchedulerPlugin = object  # type: ignore[assignment,misc]


# ------------------------------------------------------------ the registry (scheduler)


class Registry(SchedulerPlugin):  # type: ignore[misc,valid-type]
    """Job and session records inside the scheduler (see the module docstring).

    Every method runs on the scheduler's event loop, so each call is atomic. Public
    methods are called by replicas through :func:`_registry_call`; ``transition``,
    ``log_event`` and ``remove_worker`` are scheduler hooks.
    """

    name = REGISTRY_NAME
    idempotent = True

    def __init__(self) -> None:
        self.scheduler: Any = None
        self.jobs: dict[str, Job] = {}
        self.job_meta: dict[str, dict[str, Any]] = {}
        self.keys: dict[str, str] = {}
        self.failures: dict[str, dict[str, Any]] = {}
        self.sessions: dict[str, dict[str, Any]] = {}

    async def start(self, scheduler: Any) -> None:
        self.scheduler = scheduler

    # ---------------------------------------------------------------------- jobs

    def job_add(self, record: dict[str, Any], meta: dict[str, Any], max_jobs: int,
                now: float) -> int | None:
        """Store a new job unless ``max_jobs`` are stored (then return that count)."""
        self._drop_expired_jobs(now)
        if len(self.jobs) >= max_jobs:
            return len(self.jobs)
        job = Job(**record)
        self.jobs[job.id] = job
        self.job_meta[job.id] = meta
        self.keys[meta["key"]] = job.id
        return None

    async def wait_for_key(self, key: str, timeout: float) -> bool:
        """Wait until the scheduler knows task ``key`` (a client's graph and its RPCs travel
        on different connections: publishing a key before it exists would not hold it)."""
        deadline = time.monotonic() + timeout
        while key not in self.scheduler.tasks:
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(0.005)
        return True

    def job_get(self, job_id: str, now: float) -> dict[str, Any] | None:
        job = self.jobs.get(job_id)
        if job is None or (job.expires_at is not None and job.expires_at <= now):
            return None
        return _job_record(job)

    def job_finish(self, job_id: str, status: str, error: dict[str, Any] | None,
                   now: float) -> dict[str, Any] | None:
        """Finish a job from outside (cancel, timeout) unless it already finished."""
        job = self.jobs.get(job_id)
        if job is None:
            return None
        if not job.done:
            job.error = error
            job.finish(status, self.job_meta[job_id]["ttl"])
        return _job_record(job)

    def job_remove(self, job_id: str) -> bool:
        job = self.jobs.pop(job_id, None)
        meta = self.job_meta.pop(job_id, None)
        self.failures.pop(job_id, None)
        if meta is not None:
            self.keys.pop(meta["key"], None)
        return job is not None

    def job_sweep(self, now: float) -> dict[str, Any]:
        """Expire finished jobs, time out running ones; ids for the replica to clean up."""
        expired = self._drop_expired_jobs(now)
        timed_out = []
        for job_id, job in self.jobs.items():
            meta = self.job_meta[job_id]
            if not job.done and now - job.created_at > meta["timeout"]:
                job.error = ProblemError(
                    "timeout", f"the job did not finish within {meta['timeout']:g} s "
                               "(FFS_JOB_TIMEOUT)").to_dict(f"/v1/jobs/{job_id}")
                job.finish("failed", meta["ttl"])
                timed_out.append(job_id)
        return {"expired": expired, "timed_out": timed_out, "counts": self.job_counts()}

    def job_counts(self) -> dict[str, int]:
        out = dict.fromkeys(("queued", "running", "succeeded", "failed", "cancelled"), 0)
        for job in self.jobs.values():
            out[job.status] += 1
        return out

    def _drop_expired_jobs(self, now: float) -> list[str]:
        expired = [j.id for j in self.jobs.values()
                   if j.expires_at is not None and j.expires_at <= now]
        for job_id in expired:
            self.job_remove(job_id)
        return expired

    # ---------------------------------------------------------------------- hooks

    def transition(self, key: Any, start: str, finish: str, *args: Any,
                   **kwargs: Any) -> None:
        job_id = self.keys.get(key) if isinstance(key, str) else None
        if job_id is None:
            return
        job = self.jobs.get(job_id)
        if job is None or job.done:
            return
        ttl = self.job_meta[job_id]["ttl"]
        if finish == "processing":
            job.mark_running()
        elif finish == "memory":
            failure = self.failures.pop(job_id, None)
            if failure is not None:
                job.error = failure
                job.finish("failed", ttl)
            else:
                job.finish("succeeded", ttl)
        elif finish == "erred":
            job.error = _erred_problem(job_id, kwargs).to_dict(f"/v1/jobs/{job_id}")
            job.finish("failed", ttl)
        elif finish == "forgotten":
            job.finish("cancelled", ttl)

    def log_event(self, topic: str, msg: Any) -> None:
        if topic != PROGRESS_TOPIC or not isinstance(msg, dict):
            return
        job = self.jobs.get(str(msg.get("id")))
        if job is None or job.done:
            return
        if "error" in msg:
            self.failures[job.id] = msg["error"]
        elif "stage" in msg:
            job.update_progress(str(msg["stage"]), float(msg.get("fraction", 0.0)))

    def remove_worker(self, scheduler: Any = None, worker: str | None = None,
                      **kwargs: Any) -> None:
        now = time.time()
        for record in self.sessions.values():
            if record["state"] == "ready" and record.get("worker") == worker:
                self._bury(record, f"the Dask worker holding it ({worker}) left the cluster "
                                   "(it died or was stopped)", now)

    # ------------------------------------------------------------------ sessions

    def session_admit(self, session_id: str, estimate: int, max_sessions: int,
                      max_memory: int, now: float, stale_after: float,
                      ttl: float) -> dict[str, Any] | None:
        """Reserve room for a new session, or say why not (``too-many`` / ``memory``)."""
        for sid, record in list(self.sessions.items()):
            if record["state"] == "creating" and now - record["created"] > stale_after:
                del self.sessions[sid]  # its replica never finished creating it
        live = [r for r in self.sessions.values() if r["state"] in ("creating", "ready")]
        if len(live) >= max_sessions:
            return {"kind": "too-many", "count": len(live)}
        used = sum(r["memory"] for r in live)
        if used + estimate > max_memory:
            return {"kind": "memory", "used": used}
        self.sessions[session_id] = {"id": session_id, "state": "creating", "memory": estimate,
                                     "created": now, "last_used": now, "info": None,
                                     "worker": None, "reason": None, "until": None,
                                     "solves": 0, "ttl": ttl}
        return None

    def session_ready(self, session_id: str, info: dict[str, Any], memory: int, worker: str,
                      now: float, max_memory: int) -> dict[str, Any] | None:
        """Record a built session; refuse it if its measured memory breaks the cap."""
        record = self.sessions.get(session_id)
        if record is None:
            return {"kind": "gone"}
        others = sum(r["memory"] for sid, r in self.sessions.items()
                     if sid != session_id and r["state"] in ("creating", "ready"))
        if others + memory > max_memory:
            del self.sessions[session_id]
            return {"kind": "memory", "used": others}
        record.update(state="ready", info=info, memory=int(memory), worker=worker,
                      last_used=now)
        return None

    def session_get(self, session_id: str) -> dict[str, Any] | None:
        record = self.sessions.get(session_id)
        return None if record is None else dict(record)

    def session_touch(self, session_id: str, now: float, solves: int) -> None:
        record = self.sessions.get(session_id)
        if record is not None and record["state"] == "ready":
            record["last_used"] = max(record["last_used"], now)
            record["solves"] += solves

    def session_bury(self, session_id: str, reason: str, now: float) -> dict[str, Any] | None:
        record = self.sessions.get(session_id)
        if record is not None and record["state"] != "gone":
            self._bury(record, reason, now)
        return None if record is None else dict(record)

    def session_remove(self, session_id: str) -> dict[str, Any] | None:
        return self.sessions.pop(session_id, None)

    def session_sweep(self, now: float, ttl: float) -> dict[str, Any]:
        """Expire idle sessions, drop old tombstones; ids whose actors to release."""
        release = []
        for sid, record in list(self.sessions.items()):
            if record["state"] == "ready" and now - record["last_used"] > ttl:
                self._bury(record, f"it expired after {ttl:g} s without a solve "
                                   "(FFS_SESSION_TTL)", now)
            if record["state"] == "gone":
                if not record.get("released"):
                    record["released"] = True
                    release.append(sid)
                if record["until"] <= now:
                    del self.sessions[sid]
        live = [r for r in self.sessions.values() if r["state"] in ("creating", "ready")]
        gone = [sid for sid, r in self.sessions.items() if r["state"] == "gone"]
        return {"release": release, "gone": gone, "count": len(live),
                "memory": sum(r["memory"] for r in live)}

    @staticmethod
    def _bury(record: dict[str, Any], reason: str, now: float) -> None:
        record.update(state="gone", reason=reason, until=now + record["ttl"])


def _job_record(job: Job) -> dict[str, Any]:
    return {name: getattr(job, name) for name in _JOB_FIELDS}


def _erred_problem(job_id: str, kwargs: dict[str, Any]) -> ProblemError:
    """The problem of a job task that Dask marked erred (its workers died, or a bug)."""
    exception: Any = kwargs.get("exception")
    if isinstance(exception, bytes):
        with contextlib.suppress(Exception):
            exception = pickle.loads(exception)
    name = type(exception).__name__
    if name == "KilledWorker":
        attempts = getattr(exception, "allowed_failures", 0) + 1
        return ProblemError(
            "worker-died", f"the Dask workers running this job died {attempts} times (the "
            f"cluster retried it {attempts - 1} time(s), distributed.scheduler."
            f"allowed-failures); the last was {_worker_of(exception)}; the input may be too "
            "large for the memory of a worker")
    text = kwargs.get("exception_text") or str(exception)
    return ProblemError("internal-error", f"the job failed on the cluster ({name}: {text})")


def _worker_of(exception: Any) -> str:
    worker = getattr(exception, "last_worker", None)
    return str(getattr(worker, "address", worker) or "unknown")


def install_registry(scheduler: Any) -> Registry:
    """The scheduler's registry, created on first use."""
    plugin = scheduler.plugins.get(REGISTRY_NAME)
    if plugin is None:
        plugin = Registry()
        plugin.scheduler = scheduler
        scheduler.add_plugin(plugin, name=REGISTRY_NAME, idempotent=True)
        plugin = scheduler.plugins[REGISTRY_NAME]
    return plugin


def _registry_call(op: str, args: tuple[Any, ...], dask_scheduler: Any = None) -> Any:
    """Runs in the scheduler (``Client.run_on_scheduler``): one registry method."""
    return getattr(install_registry(dask_scheduler), op)(*args)


async def _registry_call_async(op: str, args: tuple[Any, ...],
                               dask_scheduler: Any = None) -> Any:
    """Like :func:`_registry_call` for the registry's coroutine methods."""
    return await getattr(install_registry(dask_scheduler), op)(*args)


def dask_setup(scheduler: Any) -> None:
    """``dask scheduler --preload service.cluster`` installs the registry at start."""
    install_registry(scheduler)


# --------------------------------------------------------------------- worker side

_initialized: set[int] = set()


def _init_worker(threads: int) -> None:
    pid = os.getpid()
    if pid not in _initialized:
        from service import tasks

        tasks.initialize_worker(threads)
        _initialized.add(pid)


class _EventProgress:
    """``progress(stage, fraction)`` -> scheduler events (stage changes, <= 5 per second)."""

    def __init__(self, job_id: str) -> None:
        from distributed import get_worker

        self.job_id = job_id
        self.worker = get_worker()
        self.stage: str | None = None
        self.last = 0.0

    def __call__(self, stage: str, fraction: float) -> None:
        now = time.monotonic()
        if stage == self.stage and now - self.last < 0.2:
            return
        self.stage, self.last = stage, now
        self.worker.log_event(PROGRESS_TOPIC, {"id": self.job_id, "stage": stage,
                                               "fraction": float(fraction)})

    def fail(self, problem: dict[str, Any]) -> None:
        self.worker.log_event(PROGRESS_TOPIC, {"id": self.job_id, "error": problem})


def run_task(fn_name: str, payload: dict[str, Any], job_id: str | None = None,
             threads: int = 1) -> dict[str, Any]:
    """A task on a Dask worker: ``{"ok": True, "result"}`` or ``{"ok": False, "error"}``."""
    from service import tasks

    _init_worker(threads)
    report = _EventProgress(job_id) if job_id else None
    try:
        result = tasks.run(fn_name, payload, report or (lambda stage, fraction: None))
    except Exception as exc:
        error = tasks.describe_error(exc)
        if report is not None:
            report.fail(from_worker_error(error).to_dict(f"/v1/jobs/{job_id}"))
        return {"ok": False, "error": error}
    return {"ok": True, "result": result}


def _rss() -> int:
    try:
        import psutil

        return int(psutil.Process().memory_info().rss)
    except Exception:
        return 0


class SessionActor:
    """A session on a Dask worker (an actor: its state stays on that worker)."""

    def __init__(self, spec: dict[str, Any], threads: int = 1) -> None:
        from distributed import get_worker

        from service import tasks
        from service.sessions import SessionState

        _init_worker(threads)
        self.worker = get_worker().address
        self.error: dict[str, Any] | None = None
        self.state: SessionState | None = None
        estimate = estimate_memory(len(spec["vertices"]), len(spec["faces"]))
        before = _rss()
        try:
            self.state = SessionState(spec)
        except Exception as exc:
            self.error = tasks.describe_error(exc)
        grown = _rss() - before
        # RSS growth of the shared worker process is a rough measure (other tasks run
        # there too); it never counts for less than half the estimate.
        self.memory = max(grown, estimate // 2)

    def info(self) -> dict[str, Any]:
        if self.state is None:
            return {"error": self.error}
        return {"info": self.state.info(), "memory": self.memory, "worker": self.worker}

    def solve(self, positions: np.ndarray, rotations: np.ndarray | None,
              fmt: str) -> tuple[str, Any, Any]:
        from service import tasks

        assert self.state is not None
        try:
            body, timings = self.state.solve(positions, rotations, fmt)
        except Exception as exc:
            return ("error", tasks.describe_error(exc), None)
        return ("ok", body, timings)


# ---------------------------------------------------------------------- replica side


class DaskConnection:
    """One async ``distributed.Client`` per app, connected in the background with retries;
    worker counts refreshed every second for readiness and capacity."""

    def __init__(self, address: str, connect_timeout: float = 30.0) -> None:
        self.address = address
        self.connect_timeout = connect_timeout
        self.client: Any = None
        self.workers = 0
        self.threads = 0
        self.connected: asyncio.Event | None = None  # made in start (needs the loop)
        self._task: asyncio.Task[None] | None = None
        self._closing = False
        self.last_error: str | None = None

    async def start(self) -> None:
        self.connected = asyncio.Event()
        self._task = asyncio.create_task(self._run())

    async def _connect(self) -> None:
        from distributed import Client

        while not self._closing:
            try:
                self.client = await Client(self.address, asynchronous=True,
                                           timeout=self.connect_timeout,
                                           name="ffs-service", set_as_default=False)
                await self.client.run_on_scheduler(_registry_call, "job_counts", ())
                self.last_error = None
                logger.info("connected to the Dask scheduler at %s", self.address)
                return
            except Exception as exc:
                self.last_error = f"{type(exc).__name__}: {exc}"
                logger.warning("cannot reach the Dask scheduler at %s (%s); retrying",
                               self.address, self.last_error)
                if self.client is not None:
                    with contextlib.suppress(Exception):
                        await self.client.close()
                    self.client = None
                await asyncio.sleep(1.0)

    async def _run(self) -> None:
        await self._connect()
        assert self.connected is not None
        self.connected.set()
        while not self._closing:
            try:
                nthreads = await asyncio.wait_for(self.client.nthreads(), 10)
                self.workers, self.threads = len(nthreads), int(sum(nthreads.values()))
            except Exception as exc:
                self.workers = self.threads = 0
                self.last_error = f"{type(exc).__name__}: {exc}"
            await asyncio.sleep(1.0)

    async def wait_connected(self, timeout: float) -> Any:
        if self.client is None or self.connected is None:
            if self.connected is None:
                raise ExecutorClosedError("the Dask backend is not running")
            try:
                await asyncio.wait_for(self.connected.wait(), timeout)
            except TimeoutError:
                raise ExecutorClosedError(
                    f"not connected to the Dask scheduler at {self.address} "
                    f"({self.last_error or 'connecting'})") from None
        return self.client

    def require(self) -> Any:
        if self.client is None:
            raise ExecutorClosedError(f"not connected to the Dask scheduler at {self.address} "
                                      f"({self.last_error or 'connecting'})")
        return self.client

    async def call(self, op: str, *args: Any) -> Any:
        """Call a :class:`Registry` method in the scheduler."""
        client = self.require()
        try:
            return await asyncio.wait_for(client.run_on_scheduler(_registry_call, op, args), 30)
        except (OSError, TimeoutError) as exc:
            raise ProblemError("unavailable", f"the Dask scheduler did not answer: {exc}",
                               headers={"Retry-After": "5"}) from None

    async def call_async(self, op: str, *args: Any) -> Any:
        """Call a coroutine method of :class:`Registry` in the scheduler."""
        client = self.require()
        try:
            return await asyncio.wait_for(
                client.run_on_scheduler(_registry_call_async, op, args), 60)
        except (OSError, TimeoutError) as exc:
            raise ProblemError("unavailable", f"the Dask scheduler did not answer: {exc}",
                               headers={"Retry-After": "5"}) from None

    async def close(self) -> None:
        self._closing = True
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
        if self.client is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.client.close(), 10)
            self.client = None


class DaskExecutor:
    """The :class:`service.executor.Executor` protocol on a Dask cluster.

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
        mean = (sum(self._durations) / len(self._durations)) if self._durations else 1.0
        return max(1, min(120, math.ceil(mean * len(self._futures) / max(1, self.size()))))

    def dask_future(self, task_id: str) -> Any:
        return self._futures.get(task_id)

    async def submit(self, fn_name: str, payload: dict[str, Any], *,
                     progress_cb: Any = None, on_start: Any = None,
                     task_id: str | None = None, job: bool = False) -> TaskHandle:
        if not self._started or self._closing:
            raise ExecutorClosedError("the worker pool is not running")
        client = self.connection.require()
        if len(self._futures) >= self.size() + self._queue_size:
            raise QueueFullError(self.retry_after())
        task_id = task_id or uuid.uuid4().hex
        key = f"{JOB_PREFIX}{task_id}" if job else f"ffs-task-{fn_name}-{task_id}"
        future = client.submit(run_task, fn_name, payload, task_id if job else None,
                               self._threads, key=key, pure=False, retries=1)
        handle: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        handle.add_done_callback(_consume)
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
            _settle(handle, exc=TaskCancelledError(f"cancelled ({exc.reason})"))
        except asyncio.CancelledError:
            _settle(handle, exc=ExecutorClosedError("the service is shutting down"))
            raise
        except Exception as exc:
            if type(exc).__name__ == "KilledWorker":
                _settle(handle, exc=WorkerDiedError(
                    f"the Dask workers running this task died {exc.args[2] + 1} times "
                    f"({exc}); the input may be too large for a worker's memory"))
            elif isinstance(exc, OSError):
                _settle(handle, exc=ExecutorClosedError(f"lost the Dask scheduler: {exc}"))
            else:
                _settle(handle, exc=TaskFailedError({
                    "category": "internal", "exception": type(exc).__name__,
                    "message": f"the task failed on the cluster: {exc}"}))
        else:
            self._durations = [*self._durations[-49:], time.monotonic() - start]
            if value.get("ok"):
                _settle(handle, result=value["result"])
            else:
                _settle(handle, exc=TaskFailedError(value["error"]))
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
        _settle(handle, exc=TaskCancelledError("cancelled"))
        return True


def _settle(handle: asyncio.Future[Any], *, result: Any = None,
            exc: BaseException | None = None) -> None:
    if handle.done():
        return
    if exc is not None:
        handle.set_exception(exc)
    else:
        handle.set_result(result)


def _consume(future: asyncio.Future[Any]) -> None:
    if not future.cancelled():
        future.exception()


class DaskJobManager:
    """:class:`service.jobs.JobService` with the job state in the scheduler."""

    def __init__(self, executor: DaskExecutor, *, ttl: float, timeout: float, max_jobs: int,
                 on_result: Any = None) -> None:
        self.executor = executor
        self.connection = executor.connection
        self.ttl = ttl
        self.timeout = timeout
        self.max_jobs = max_jobs
        self._on_result = on_result
        self._counts: dict[str, int] = dict.fromkeys(
            ("queued", "running", "succeeded", "failed", "cancelled"), 0)
        self._watchers: set[asyncio.Task[None]] = set()
        self._sweeper: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._sweeper = asyncio.create_task(self._sweep())

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

    async def _sweep(self) -> None:
        await sweep_forever(self.connection, self.ttl, self.sweep, "job sweeper")

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

    async def submit(self, operation: str, payload: dict[str, Any], *,
                     color: str | None = None, task: str | None = None) -> Job:
        try:
            client = await self.connection.wait_connected(5.0)
        except ExecutorClosedError as exc:
            raise ProblemError("unavailable", str(exc), headers={"Retry-After": "5"}) from exc
        job = Job(id=uuid.uuid4().hex, operation=operation, color=color)
        meta = {"key": JOB_PREFIX + job.id, "ttl": self.ttl, "timeout": self.timeout}
        full = await self.connection.call("job_add", _job_record(job), meta, self.max_jobs,
                                          time.time())
        if full is not None:
            raise ProblemError("too-many-jobs",
                               f"{full} jobs are stored (limit {self.max_jobs}); fetch or "
                               "delete finished jobs, or retry later",
                               headers={"Retry-After": "5"})
        try:
            handle = await self.executor.submit(task or operation, payload, task_id=job.id,
                                                job=True)
            if not await self.connection.call_async("wait_for_key", meta["key"], 30.0):
                raise ExecutorClosedError("the Dask scheduler did not receive the job")
            await client.publish_dataset(self.executor.dask_future(job.id),
                                         name=JOB_PREFIX + job.id)
        except BaseException as exc:
            with contextlib.suppress(Exception):
                await self.connection.call("job_remove", job.id)
            if isinstance(exc, QueueFullError):
                raise queue_full_problem(exc) from exc
            if isinstance(exc, ExecutorClosedError):
                raise ProblemError("unavailable", str(exc),
                                   headers={"Retry-After": "5"}) from exc
            raise
        watcher = asyncio.create_task(self._watch(job, handle.future))
        self._watchers.add(watcher)
        watcher.add_done_callback(self._watchers.discard)
        return job

    async def _watch(self, job: Job, future: asyncio.Future[Any]) -> None:
        """Metrics for jobs this replica submitted (their state is the registry's)."""
        with contextlib.suppress(Exception):
            result = await asyncio.wait_for(asyncio.shield(future), self.timeout)
            if self._on_result is not None:
                self._on_result(job.operation, result)

    async def get(self, job_id: str) -> Job | None:
        record = await self.connection.call("job_get", job_id, time.time())
        return None if record is None else Job(**record)

    async def result(self, job: Job) -> dict[str, Any]:
        client = self.connection.require()
        future = await client.get_dataset(JOB_PREFIX + job.id, default=None)
        if future is None:
            raise ProblemError("not-found", f"the result of job {job.id} is gone (it expired)")
        try:
            value = await asyncio.wait_for(future, 60)
        except Exception as exc:
            raise ProblemError("job-failed", f"job {job.id}: its result could not be fetched "
                               f"from the cluster ({type(exc).__name__}: {exc})") from None
        if not value.get("ok"):
            raise from_worker_error(value["error"])
        return value["result"]

    async def cancel(self, job: Job) -> None:
        record = await self.connection.call("job_finish", job.id, "cancelled", None,
                                            time.time())
        if record is not None:
            for name in _JOB_FIELDS:
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


class DaskSessions:
    """:class:`service.sessions.SessionBackend` with each session a Dask actor."""

    name = "dask"

    def __init__(self, connection: DaskConnection, *, ttl: float, max_sessions: int,
                 max_memory: int, threads: int, solve_timeout: float,
                 setup_timeout: float) -> None:
        self.connection = connection
        self.ttl = ttl
        self.max_sessions = max_sessions
        self.max_memory = max_memory
        self.threads = threads
        self.solve_timeout = solve_timeout
        self.setup_timeout = setup_timeout
        self._actors: dict[str, Any] = {}
        self._futures: dict[str, Any] = {}
        self._shapes: dict[str, tuple[int, int]] = {}
        self._unsent: dict[str, int] = {}
        self._touched: dict[str, float] = {}
        self._background: set[asyncio.Task[None]] = set()
        self._count = 0
        self._memory = 0
        self._sweeper: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._sweeper = asyncio.create_task(self._sweep())

    async def stop(self) -> None:
        if self._sweeper is not None:
            self._sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._sweeper
        self._actors.clear()
        self._futures.clear()

    def count(self) -> int:
        return self._count

    def memory(self) -> int:
        return self._memory

    async def _sweep(self) -> None:
        await sweep_forever(self.connection, self.ttl, self.expire, "session sweeper")

    async def expire(self) -> None:
        await self._flush_touches(force=True)
        swept = await self.connection.call("session_sweep", time.time(), self.ttl)
        self._count, self._memory = swept["count"], swept["memory"]
        for session_id in swept["release"]:
            await self._release(session_id)
        for session_id in swept["gone"]:
            self._forget(session_id)

    def _forget(self, session_id: str) -> None:
        self._actors.pop(session_id, None)
        self._futures.pop(session_id, None)
        self._shapes.pop(session_id, None)
        self._unsent.pop(session_id, None)
        self._touched.pop(session_id, None)

    async def _release(self, session_id: str) -> None:
        self._forget(session_id)
        client = self.connection.client
        if client is not None:
            with contextlib.suppress(KeyError, Exception):
                await client.unpublish_dataset(SESSION_PREFIX + session_id)

    def _touch(self, session_id: str) -> None:
        """Count a drag; tell the registry at most once a second (off the drag's path)."""
        self._unsent[session_id] = self._unsent.get(session_id, 0) + 1
        now = time.monotonic()
        if now - self._touched.get(session_id, 0.0) >= min(1.0, self.ttl / 10):
            self._touched[session_id] = now
            task = asyncio.create_task(self._flush_touches(only=session_id))
            self._background.add(task)
            task.add_done_callback(self._background.discard)

    async def _flush_touches(self, force: bool = False, only: str | None = None) -> None:
        ids = [only] if only is not None else list(self._unsent)
        for session_id in ids:
            solves = self._unsent.pop(session_id, 0)
            if solves or force:
                with contextlib.suppress(Exception):
                    await self.connection.call("session_touch", session_id, time.time(),
                                               solves)

    # --------------------------------------------------------------------- create

    async def create(self, spec: dict[str, Any]) -> dict[str, Any]:
        try:
            client = await self.connection.wait_connected(5.0)
        except ExecutorClosedError as exc:
            raise ProblemError("unavailable", str(exc), headers={"Retry-After": "5"}) from exc
        session_id = uuid.uuid4().hex
        estimate = estimate_memory(len(spec["vertices"]), len(spec["faces"]))
        refusal = await self.connection.call("session_admit", session_id, estimate,
                                             self.max_sessions, self.max_memory, time.time(),
                                             self.setup_timeout + 30, self.ttl)
        if refusal is not None:
            if refusal["kind"] == "too-many":
                raise too_many(refusal["count"], self.max_sessions,
                               max(1, min(120, math.ceil(self.ttl / 4))))
            raise memory_problem(refusal["used"], estimate, self.max_memory)
        future = None
        try:
            future = client.submit(SessionActor, spec, self.threads, actors=True, pure=False,
                                   key=SESSION_PREFIX + session_id)
            try:
                with client.as_current():  # the actor proxy binds to this app's client
                    actor = await asyncio.wait_for(future, self.setup_timeout)
                built = await asyncio.wait_for(actor.info(), self.setup_timeout)
            except TimeoutError:
                raise ProblemError("timeout", f"the session was not ready within "
                                   f"{self.setup_timeout:g} s (FFS_REQUEST_TIMEOUT)") from None
            except ProblemError:
                raise
            except Exception as exc:
                raise _actor_failure(exc) from None
            if built.get("error") is not None:
                raise from_worker_error(built["error"])
            await client.publish_dataset(future, name=SESSION_PREFIX + session_id)
            refusal = await self.connection.call(
                "session_ready", session_id, built["info"], int(built["memory"]),
                built["worker"], time.time(), self.max_memory)
            if refusal is not None:
                with contextlib.suppress(Exception):
                    await client.unpublish_dataset(SESSION_PREFIX + session_id)
                raise memory_problem(refusal.get("used", 0), int(built["memory"]),
                                     self.max_memory)
        except BaseException:
            with contextlib.suppress(Exception):
                await self.connection.call("session_remove", session_id)
            if future is not None:
                with contextlib.suppress(Exception):
                    await client.cancel([future], force=True)
            raise
        info = built["info"]
        self._actors[session_id] = actor
        self._futures[session_id] = future
        self._shapes[session_id] = (len(info["handles"]), int(info["n_rotation_groups"]))
        self._count += 1
        self._memory += int(built["memory"])
        return session_document(session_id, info, expires_in=self.ttl, backend=self.name,
                                memory=int(built["memory"]), solves=0)

    # ---------------------------------------------------------------------- state

    async def _record(self, session_id: str) -> dict[str, Any]:
        record = await self.connection.call("session_get", session_id)
        if record is None or record["state"] == "creating":
            self._forget(session_id)
            raise not_found(session_id)
        if record["state"] == "gone":
            self._forget(session_id)
            raise gone_problem(session_id, record["reason"])
        return record

    async def describe(self, session_id: str) -> dict[str, Any]:
        await self._flush_touches(only=session_id)
        record = await self._record(session_id)
        expires = self.ttl - (time.time() - record["last_used"])
        return session_document(session_id, record["info"], expires_in=expires,
                                backend=self.name, memory=record["memory"],
                                solves=record["solves"])

    async def shape(self, session_id: str) -> tuple[int, int]:
        shape = self._shapes.get(session_id)
        if shape is None:
            info = (await self._record(session_id))["info"]
            shape = self._shapes[session_id] = (len(info["handles"]),
                                                int(info["n_rotation_groups"]))
        return shape

    async def _actor(self, session_id: str) -> Any:
        actor = self._actors.get(session_id)
        if actor is not None:
            return actor
        await self._record(session_id)
        client = self.connection.require()
        future = await client.get_dataset(SESSION_PREFIX + session_id, default=None)
        if future is None:
            raise not_found(session_id)
        try:
            with client.as_current():
                actor = await asyncio.wait_for(future, 10)
        except Exception as exc:
            await self._bury(session_id, _actor_failure(exc).detail)
            raise gone_problem(session_id, _actor_failure(exc).detail) from None
        self._actors[session_id] = actor
        self._futures[session_id] = future
        return actor

    async def _bury(self, session_id: str, reason: str) -> str:
        record = await self.connection.call("session_bury", session_id, reason, time.time())
        await self._release(session_id)
        return (record or {}).get("reason") or reason

    async def solve(self, session_id: str, positions: np.ndarray,
                    rotations: np.ndarray | None, fmt: str) -> tuple[bytes, dict[str, float]]:
        actor = await self._actor(session_id)
        try:
            status, body, timings = await asyncio.wait_for(
                actor.solve(positions, rotations, fmt), self.solve_timeout)
        except TimeoutError:
            await self._bury(session_id, f"a solve took longer than {self.solve_timeout:g} s "
                                         "(FFS_SESSION_SOLVE_TIMEOUT)")
            raise ProblemError("timeout", f"no result within {self.solve_timeout:g} s "
                               "(FFS_SESSION_SOLVE_TIMEOUT); the session was closed") from None
        except Exception as exc:
            record = await self.connection.call("session_get", session_id)
            if record is None:
                self._forget(session_id)
                raise not_found(session_id) from None
            if record["state"] == "gone":
                await self._release(session_id)
                raise gone_problem(session_id, record["reason"]) from None
            reason = await self._bury(session_id, _actor_failure(exc).detail)
            raise gone_problem(session_id, reason) from None
        if status != "ok":
            raise from_worker_error(body)
        self._touch(session_id)
        return body, timings

    async def delete(self, session_id: str) -> None:
        record = await self.connection.call("session_remove", session_id)
        await self._release(session_id)
        if record is None:
            raise not_found(session_id)
        if record["state"] == "ready":
            self._count = max(0, self._count - 1)
            self._memory = max(0, self._memory - int(record["memory"]))


def _actor_failure(exc: BaseException) -> ProblemError:
    text = str(exc) or type(exc).__name__
    if "lost" in text.lower() or isinstance(exc, OSError):
        reason = f"the Dask worker holding it died ({text})"
    else:
        reason = f"the session's actor failed ({type(exc).__name__}: {text})"
    return ProblemError("worker-died", reason)


def make_backend(settings: Any) -> tuple[DaskExecutor, DaskJobManager, DaskSessions]:
    """Executor, job manager and session backend sharing one Dask client."""
    connection = DaskConnection(settings.dask_scheduler_address,
                                connect_timeout=settings.dask_connect_timeout)
    threads = settings.threads_per_worker or 1
    executor = DaskExecutor(connection, settings.queue_size, threads)
    jobs = DaskJobManager(executor, ttl=settings.job_ttl, timeout=settings.job_timeout,
                          max_jobs=settings.max_jobs)
    sessions = DaskSessions(connection, ttl=settings.session_ttl,
                            max_sessions=settings.max_sessions,
                            max_memory=settings.max_session_memory,
                            threads=settings.session_threads or 1,
                            solve_timeout=settings.session_solve_timeout,
                            setup_timeout=settings.request_timeout)
    return executor, jobs, sessions
