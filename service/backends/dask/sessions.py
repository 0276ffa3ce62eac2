"""Deformation sessions on a Dask cluster: :class:`DaskSessions`.

Each session is a Dask actor (:class:`~service.backends.dask.worker.SessionActor`, one
:class:`~service.worker.session.SessionState` each) pinned to the worker that built it and
held by a published dataset ``ffs-session-{id}``. The registry admits sessions against
FFS_MAX_SESSIONS, FFS_MAX_SESSION_MEMORY and FFS_MAX_CLIENT_SESSIONS atomically (idle ones
giving way, their actors released by the admitting replica), tracks their last use, expires idle
ones and buries the sessions of a worker that leaves the cluster (gone afterwards).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
import uuid
from typing import Any

import numpy as np

from service.api.task import SessionSpec
from service.backends import errors
from service.backends.admission import estimate_memory
from service.backends.contracts import DragAnswer, SessionPolicy, SessionRecord
from service.backends.dask.connection import DaskConnection
from service.backends.dask.registry import SESSION_PREFIX
from service.backends.dask.worker import SessionActor
from service.backends.loops import sweep_forever

WATCH_SECONDS = 1.0
"""How often a pending actor call looks at the registry for its session's burial."""


class _BuriedError(Exception):
    """The registry buried the session while one of its actor calls was pending."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class DaskSessions:
    """The :class:`~service.backends.contracts.SessionBackend` with each session a Dask
    actor (see the module docstring)."""

    name = "dask"

    def __init__(self, connection: DaskConnection, policy: SessionPolicy) -> None:
        self.connection, self.policy = connection, policy
        self._actors: dict[str, Any] = {}
        self._futures: dict[str, Any] = {}
        self._shapes: dict[str, tuple[int, int]] = {}
        self._owners: dict[str, str | None] = {}
        """Owners seen by this replica (an owner never changes: one registry call each)."""
        self._unsent: dict[str, int] = {}
        self._touched: dict[str, float] = {}
        self._background: set[asyncio.Task[None]] = set()
        self._count = 0
        self._memory = 0
        self._sweeper: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._sweeper = asyncio.create_task(sweep_forever(
            self.policy.ttl, self.expire, "session sweeper", active=self.connection.connected_now))

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

    async def expire(self) -> None:
        await self._flush_touches(force=True)
        swept = await self.connection.call("session_sweep", time.time(), self.policy.ttl)
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
        self._owners.pop(session_id, None)
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
        if now - self._touched.get(session_id, 0.0) >= min(1.0, self.policy.ttl / 10):
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

    async def create(self, spec: SessionSpec, owner: str | None = None,
                     max_per_owner: int | None = None) -> SessionRecord:
        client = await self.connection.wait_connected(5.0)
        session_id = uuid.uuid4().hex
        estimate = estimate_memory(len(spec.vertices), len(spec.faces))
        policy = self.policy
        answer = await self.connection.call("session_admit", session_id, estimate,
                                            policy.max_sessions, policy.max_memory,
                                            time.time(), policy.setup_timeout + 30, policy.ttl,
                                            owner, max_per_owner or policy.max_per_client,
                                            policy.give_way_after)
        kind = None if answer is None else answer["kind"]
        if kind == "too-many":
            raise errors.TooManySessionsError(answer["count"], policy.max_sessions,
                                              answer["retry_after"])
        if kind == "memory":
            raise errors.SessionMemoryError(answer["used"], estimate, policy.max_memory)
        if kind == "client":
            raise errors.ClientSessionsError(max_per_owner or policy.max_per_client)
        for evicted in (answer or {}).get("evict", ()):
            await self._release(evicted)
            self._count = max(0, self._count - 1)
        future = None
        try:
            future = client.submit(SessionActor, spec, self.policy.threads,
                                   policy.solve_timeout, policy.refine_slice, actors=True,
                                   pure=False, key=SESSION_PREFIX + session_id)
            try:
                with client.as_current():  # the actor proxy binds to this app's client
                    actor = await asyncio.wait_for(future, self.policy.setup_timeout)
                built = await asyncio.wait_for(actor.info(), self.policy.setup_timeout)
            except TimeoutError:
                raise errors.DeadlineError(
                    f"the session was not ready within {self.policy.setup_timeout:g} s "
                    "(FFS_REQUEST_TIMEOUT)") from None
            except errors.BackendError:
                raise
            except Exception as exc:
                raise errors.WorkerDiedError(_actor_failure(exc)) from None
            if built.get("error") is not None:
                raise errors.TaskFailedError(built["error"])
            await client.publish_dataset(future, name=SESSION_PREFIX + session_id)
            refusal = await self.connection.call(
                "session_ready", session_id, built["info"], int(built["memory"]),
                built["worker"], time.time(), self.policy.max_memory)
            if refusal is not None:
                with contextlib.suppress(Exception):
                    await client.unpublish_dataset(SESSION_PREFIX + session_id)
                raise errors.SessionMemoryError(refusal.get("used", 0), int(built["memory"]),
                                         self.policy.max_memory)
        except BaseException:
            with contextlib.suppress(Exception):
                await self.connection.call("session_remove", session_id)
            if future is not None:
                with contextlib.suppress(Exception):
                    await client.cancel([future], force=True)
            raise
        info = built["info"]
        self._owners[session_id] = owner
        self._actors[session_id] = actor
        self._futures[session_id] = future
        self._shapes[session_id] = (len(info["handles"]), int(info["n_rotation_groups"]))
        self._count += 1
        self._memory += int(built["memory"])
        return SessionRecord(session_id, info, self.policy.ttl, int(built["memory"]), 0, self.name)

    # ---------------------------------------------------------------------- state

    async def _record(self, session_id: str) -> dict[str, Any]:
        record = await self.connection.call("session_get", session_id)
        if record is None or record["state"] == "creating":
            self._forget(session_id)
            raise errors.SessionNotFoundError(session_id)
        if record["state"] == "gone":
            self._forget(session_id)
            raise errors.SessionGoneError(session_id, record["reason"])
        return record

    async def describe(self, session_id: str) -> SessionRecord:
        await self._flush_touches(only=session_id)
        record = await self._record(session_id)
        expires = self.policy.ttl - (time.time() - record["last_used"])
        return SessionRecord(session_id, record["info"], max(0.0, expires), record["memory"],
                             record["solves"], self.name)

    async def owner(self, session_id: str) -> str | None:
        if session_id in self._owners:
            return self._owners[session_id]
        record = await self.connection.call("session_get", session_id)
        if record is None or record["state"] == "creating":
            raise errors.SessionNotFoundError(session_id)
        owner = self._owners[session_id] = record.get("owner")
        return owner

    async def list(self, owner: str | None = None) -> list[SessionRecord]:
        await self._flush_touches(force=True)
        now = time.time()
        return [SessionRecord(r["id"], r["info"],
                              max(0.0, self.policy.ttl - (now - r["last_used"])), r["memory"],
                              r["solves"], self.name)
                for r in await self.connection.call("session_list", owner)]

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
            raise errors.SessionNotFoundError(session_id)
        try:
            with client.as_current():
                actor = await asyncio.wait_for(future, 10)
        except Exception as exc:
            await self._bury(session_id, _actor_failure(exc))
            raise errors.SessionGoneError(session_id, _actor_failure(exc)) from None
        self._actors[session_id] = actor
        self._futures[session_id] = future
        return actor

    async def _bury(self, session_id: str, reason: str) -> str:
        record = await self.connection.call("session_bury", session_id, reason, time.time())
        await self._release(session_id)
        return (record or {}).get("reason") or reason

    async def _released(self, session_id: str, reason: str) -> errors.SessionGoneError:
        """Release this replica's handles of a session the registry has buried, and return
        the 410 to raise (``reason`` is the registry's)."""
        await self._release(session_id)
        return errors.SessionGoneError(session_id, reason)

    async def solve(self, session_id: str, positions: np.ndarray,
                    rotations: np.ndarray | None, fmt: str) -> DragAnswer:
        actor = await self._actor(session_id)
        try:
            status, body, timings, *drag = await self._watched(
                session_id, actor.solve(positions, rotations, fmt), self.policy.solve_timeout)
        except _BuriedError as gone:
            raise await self._released(session_id, gone.reason) from None
        except TimeoutError:
            await self._bury(session_id, f"a solve took longer than "
                                         f"{self.policy.solve_timeout:g} s "
                                         "(FFS_SESSION_SOLVE_TIMEOUT)")
            raise errors.DeadlineError(f"no result within {self.policy.solve_timeout:g} s "
                                "(FFS_SESSION_SOLVE_TIMEOUT); the session was closed") from None
        except Exception as exc:
            record = await self.connection.call("session_get", session_id)
            if record is None:
                self._forget(session_id)
                raise errors.SessionNotFoundError(session_id) from None
            if record["state"] == "gone":
                raise await self._released(session_id, record["reason"]) from None
            reason = await self._bury(session_id, _actor_failure(exc))
            raise errors.SessionGoneError(session_id, reason) from None
        if status != "ok":
            raise errors.TaskFailedError(body)
        self._touch(session_id)
        return DragAnswer(body, timings, drag[0], drag[1])

    async def _watched(self, session_id: str, call: Any, timeout: float) -> Any:
        """Await an actor ``call`` for at most ``timeout`` seconds while watching the
        registry: when the session is buried meanwhile (its worker left the cluster, which
        the scheduler's ``remove_worker`` hook records), raise :class:`_BuriedError` at once
        instead of waiting for a connection to a dead worker to time out."""
        task = asyncio.ensure_future(call)
        deadline = time.monotonic() + timeout
        try:
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError
                done, _ = await asyncio.wait({task}, timeout=min(WATCH_SECONDS, left))
                if done:
                    return task.result()
                record = await self.connection.call("session_get", session_id)
                if record is not None and record["state"] == "gone":
                    raise _BuriedError(record["reason"])
        finally:
            if not task.done():
                task.cancel()

    async def refined(self, session_id: str, drag: int, wait: float) -> Any:
        """Polls the actor (every 10 ms) until the drag's refinement is settled or ``wait``
        seconds passed."""
        actor = await self._actor(session_id)
        deadline = time.monotonic() + wait
        while True:
            try:
                status, value = await self._watched(session_id, actor.refined(drag), 10.0)
            except TimeoutError:  # the worker's actor thread is busy: still refining
                status, value = "refining", None
            except _BuriedError as gone:
                raise await self._released(session_id, gone.reason) from None
            except Exception as exc:
                reason = await self._bury(session_id, _actor_failure(exc))
                raise errors.SessionGoneError(session_id, reason) from None
            if status == "refined":
                return value
            if status == "failed":
                raise errors.TaskFailedError(value)
            if status == "superseded":
                raise errors.DragSupersededError(session_id, drag, int(value))
            if status == "none":
                raise errors.DragNotFoundError(session_id, drag, str(value))
            if time.monotonic() >= deadline:
                return None
            await asyncio.sleep(min(0.01, max(0.0, deadline - time.monotonic())))

    async def delete(self, session_id: str) -> None:
        record = await self.connection.call("session_remove", session_id)
        await self._release(session_id)
        if record is None:
            raise errors.SessionNotFoundError(session_id)
        if record["state"] == "ready":
            self._count = max(0, self._count - 1)
            self._memory = max(0, self._memory - int(record["memory"]))


def _actor_failure(exc: BaseException) -> str:
    """Why a session's actor is unusable, from the exception its call raised."""
    text = str(exc) or type(exc).__name__
    if "lost" in text.lower() or isinstance(exc, OSError):
        return f"the Dask worker holding it died ({text})"
    return f"the session's actor failed ({type(exc).__name__}: {text})"
