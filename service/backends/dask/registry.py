"""The Dask backend's state, inside the scheduler: :class:`Registry`.

A scheduler plugin keeps the job records and follows their tasks' transitions (queued ->
running -> succeeded / failed / cancelled) itself, so a job does not depend on the replica
that submitted it. Workers send progress as scheduler events (``Worker.log_event``,
batched, non-blocking); the plugin folds them into the record. It also admits sessions
against FFS_MAX_SESSIONS, FFS_MAX_SESSION_MEMORY and FFS_MAX_CLIENT_SESSIONS atomically
(idle ones giving way), tracks their last use,
expires idle ones and buries the sessions of a worker that leaves the cluster.

Replicas reach it with ``Client.run_on_scheduler`` (:func:`registry_call`); the first call
installs the plugin (or ``dask scheduler --preload service.backends.dask`` does at start).
"""

from __future__ import annotations

import asyncio
import contextlib
import pickle
import time
from typing import Any

from service.api.problems import failure
from service.backends.admission import SessionAdmission, SessionSlot, admit_session
from service.backends.errors import (
    ClientSessionsError,
    SessionMemoryError,
    TooManySessionsError,
)
from service.backends.jobs import Job, admit, count_states, job_fields

REGISTRY_NAME = "ffs-registry"
PROGRESS_TOPIC = "ffs-job"
JOB_PREFIX = "ffs-job-"
SESSION_PREFIX = "ffs-session-"

try:  # the plugin base class; without dask the module still imports (for docs/tests)
    from distributed.diagnostics.plugin import SchedulerPlugin
except ImportError:  # pragma: no cover - dask is an optional extra
    SchedulerPlugin = object  # type: ignore[assignment,misc]


class Registry(SchedulerPlugin):  # type: ignore[misc,valid-type]
    """Job and session records inside the scheduler (see the module docstring).

    Every method runs on the scheduler's event loop, so each call is atomic. Public
    methods are called by replicas through :func:`registry_call`; ``transition``,
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
                now: float, max_per_owner: int = 16) -> int | str | None:
        """Store a new job (the oldest finished ones give way, :func:`admit`); else the
        number of unfinished jobs (the store is full of them) or ``"owner"`` (its client
        has ``max_per_owner`` unfinished jobs)."""
        self._drop_expired_jobs(now)
        evict, refusal = admit(self.jobs.values(), max_jobs, record.get("owner"),
                               max_per_owner)
        if refusal == "owner":
            return refusal
        if refusal is not None:
            return len(self.jobs)
        for job_id in evict:
            self.job_remove(job_id)
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
        return job_fields(job)

    def job_list(self, owner: str | None, now: float) -> list[dict[str, Any]]:
        """The records of ``owner``'s unexpired jobs (every owner's when None), oldest
        first."""
        return [job_fields(j) for j in sorted(self.jobs.values(), key=lambda j: j.created_at)
                if (owner is None or j.owner == owner)
                and (j.expires_at is None or j.expires_at > now)]

    def job_finish(self, job_id: str, status: str, error: dict[str, Any] | None,
                   now: float) -> dict[str, Any] | None:
        """Finish a job from outside (cancel, timeout) unless it already finished."""
        job = self.jobs.get(job_id)
        if job is None:
            return None
        if not job.done:
            job.error = error
            job.finish(status, self.job_meta[job_id]["ttl"])
        return job_fields(job)

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
                job.error = failure("timeout", f"the job did not finish within "
                                               f"{meta['timeout']:g} s (FFS_JOB_TIMEOUT)")
                job.finish("failed", meta["ttl"])
                timed_out.append(job_id)
        return {"expired": expired, "timed_out": timed_out, "counts": self.job_counts()}

    def job_counts(self) -> dict[str, int]:
        return count_states(self.jobs.values())

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
            job.error = _erred_failure(kwargs)
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
            job.update_progress(str(msg["stage"]), float(msg.get("fraction", 0.0)),
                                msg.get("detail"))

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
                      ttl: float, owner: str | None = None, max_per_owner: int = 10_000,
                      give_way_after: float = float("inf")) -> dict[str, Any] | None:
        """Reserve room for a new session of client ``owner`` (:func:`admit_session`), or say
        why not (``kind``: ``too-many`` with ``retry_after``, ``memory``, ``client``). Idle
        sessions that give way are buried here: ``{"kind": "admitted", "evict": ids}`` (the
        caller releases their actors); None when nothing had to give way."""
        for sid, record in list(self.sessions.items()):
            if record["state"] == "creating" and now - record["created"] > stale_after:
                del self.sessions[sid]  # its replica never finished creating it
        slots = [SessionSlot(sid, r.get("owner"), r["memory"],
                             now - r["last_used"] if r["state"] == "ready" else None)
                 for sid, r in self.sessions.items() if r["state"] in ("creating", "ready")]
        limits = SessionAdmission(max_sessions, max_memory, max_per_owner, give_way_after, ttl)
        try:
            evict = admit_session(slots, owner, estimate, limits)
        except TooManySessionsError as exc:
            return {"kind": "too-many", "count": exc.count, "retry_after": exc.retry_after}
        except SessionMemoryError as exc:
            return {"kind": "memory", "used": exc.used}
        except ClientSessionsError:
            return {"kind": "client", "limit": max_per_owner}
        for sid in evict:
            record = self.sessions[sid]
            self._bury(record, f"it gave way to a new session after "
                               f"{now - record['last_used']:.0f} s without a drag (the open "
                               "sessions were at FFS_MAX_SESSIONS or FFS_MAX_SESSION_MEMORY; "
                               "FFS_SESSION_GIVE_WAY)", now)
            record["released"] = True  # (by the caller)
        self.sessions[session_id] = {"id": session_id, "state": "creating", "memory": estimate,
                                     "created": now, "last_used": now, "info": None,
                                     "worker": None, "reason": None, "until": None,
                                     "solves": 0, "ttl": ttl, "owner": owner}
        return {"kind": "admitted", "evict": evict} if evict else None

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

    def session_list(self, owner: str | None) -> list[dict[str, Any]]:
        """The records of ``owner``'s ready sessions (every owner's when None)."""
        return [dict(r) for r in self.sessions.values()
                if r["state"] == "ready" and (owner is None or r.get("owner") == owner)]

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


def _erred_failure(kwargs: dict[str, Any]) -> dict[str, Any]:
    """The failure of a job task that Dask marked erred (its workers died, or a bug)."""
    exception: Any = kwargs.get("exception")
    if isinstance(exception, bytes):
        with contextlib.suppress(Exception):
            exception = pickle.loads(exception)
    name = type(exception).__name__
    if name == "KilledWorker":
        attempts = getattr(exception, "allowed_failures", 0) + 1
        return failure(
            "worker-died", f"the Dask workers running this job died {attempts} times (the "
            f"cluster retried it {attempts - 1} time(s), distributed.scheduler."
            f"allowed-failures); the last was {_worker_of(exception)}; the input may be too "
            "large for the memory of a worker")
    text = kwargs.get("exception_text") or str(exception)
    return failure("internal-error", f"the job failed on the cluster ({name}: {text})")


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


def registry_call(op: str, args: tuple[Any, ...], dask_scheduler: Any = None) -> Any:
    """Runs in the scheduler (``Client.run_on_scheduler``): one registry method."""
    return getattr(install_registry(dask_scheduler), op)(*args)


async def registry_call_async(op: str, args: tuple[Any, ...],
                               dask_scheduler: Any = None) -> Any:
    """Like :func:`registry_call` for the registry's coroutine methods."""
    return await getattr(install_registry(dask_scheduler), op)(*args)
