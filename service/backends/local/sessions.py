"""Local deformation sessions: one dedicated process per session (:class:`LocalSessions`).

``create`` starts a :class:`~service.backends.processes.WorkerProcess` outside the stateless
task pool, which builds a :class:`~service.worker.session.SessionState` (the factorization)
and then serves solves over its own pipe. A crash, an OOM kill or a solve beyond
``FFS_SESSION_SOLVE_TIMEOUT`` ends only that session, which then answers
:class:`SessionGoneError`. A progressive session's process refines its newest drag in
slices between drags (:meth:`SessionState.refine_slice
<service.worker.session.SessionState.refine_slice>`) and sends the refined shape unasked.
Idle sessions close after ``FFS_SESSION_TTL`` seconds; a session
that expired or whose process died stays "gone" for another TTL, then it is unknown.
Admission: :mod:`service.backends.sessions`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import logging
import time
import uuid
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from service.api.problems import failure_of
from service.api.task import SessionSpec
from service.backends import errors
from service.backends.admission import SessionSlot, admit_session, estimate_memory
from service.backends.contracts import DragAnswer, SessionPolicy, SessionRecord
from service.backends.loops import new_future, settle, sweep_forever
from service.backends.processes import Message, WorkerProcess
from service.memory import process_memory

logger = logging.getLogger("service.sessions")


def _session_main(conn: Connection, threads: int, solve_timeout: float,
                  refine_slice: float) -> None:
    """Entry point of a local session process: build the session, then serve solves;
    between them (no drag waiting on the pipe, none for DRAG_PAUSE after the last one)
    refine the newest drag slice by slice."""
    from service.worker import runtime

    runtime.start_worker_process(threads)
    from service.api.problems import failure_of
    from service.worker.session import SessionState

    try:
        spec = conn.recv()
        try:
            state = SessionState(spec, solve_timeout)
        except Exception as exc:
            conn.send(("error", failure_of(exc)))
            return
        del spec
        conn.send(("ready", state.info(), process_memory()))
        while True:
            if state.pending is not None and not conn.poll(state.refine_due()):
                drag = state.pending.drag
                try:
                    refined = state.refine_slice(refine_slice)
                except Exception as exc:
                    state.pending = None
                    conn.send(("refine-error", drag, failure_of(exc)))
                else:
                    if refined is not None:
                        conn.send(("refined", refined))
                continue
            message = conn.recv()
            if message is None:
                return
            positions, rotations, fmt = message
            try:
                body, timings, drag = state.solve(positions, rotations, fmt)
            except Exception as exc:
                conn.send(("error", failure_of(exc)))
            else:
                conn.send(("ok", body, timings, drag, state.pending is not None))
    except (EOFError, OSError):  # the service went away
        return


@dataclass
class _LocalSession:
    id: str
    proc: WorkerProcess
    info: dict[str, Any]
    memory: int
    owner: str | None = None
    last_used: float = field(default_factory=time.monotonic)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    pending: asyncio.Future[Any] | None = None
    alive: bool = True
    closing: bool = False
    reason: str | None = None
    solves: int = 0
    drag: int = 0
    """The newest drag answered (its number in the session process)."""
    refining: bool = False
    """Whether the newest drag's refined shape is still to come."""
    refined: tuple[int, Any] | None = None
    """(drag, :class:`Refined` or failure dict) of the newest drag, once refined."""
    changed: asyncio.Event = field(default_factory=asyncio.Event)
    """Set (and replaced) whenever a drag or refined shape arrives."""


class LocalSessions:
    """One dedicated process per session (see the module docstring)."""

    name = "local"

    def __init__(self, policy: SessionPolicy, start_method: str = "forkserver") -> None:
        self.policy = policy
        self.start_method = start_method
        self._sessions: dict[str, _LocalSession] = {}
        self._gone: dict[str, tuple[str, float]] = {}
        self._owners: dict[str, str | None] = {}
        """Who created each live or gone session (ownership outlives the process)."""
        self._reserved: dict[str, SessionSlot] = {}
        """Sessions being built: admission counts them (never idle)."""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._sweeper: asyncio.Task[None] | None = None
        self.deaths = 0

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._sweeper = asyncio.create_task(
            sweep_forever(self.policy.ttl, self.expire, "session sweeper", ceiling=10.0))

    async def stop(self) -> None:
        if self._sweeper is not None:
            self._sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._sweeper
        sessions = list(self._sessions.values())
        self._sessions.clear()
        await asyncio.gather(*(asyncio.to_thread(self._close, s) for s in sessions))

    async def expire(self) -> int:
        """Close sessions idle for longer than the TTL; drop old tombstones."""
        now = time.monotonic()
        idle = [s for s in self._sessions.values()
                if s.alive and not s.lock.locked() and now - s.last_used > self.policy.ttl]
        for s in idle:
            self._bury(s, f"it expired after {self.policy.ttl:g} s without a solve "
                          "(FFS_SESSION_TTL)")
            await asyncio.to_thread(self._close, s)
        for sid, (_, until) in list(self._gone.items()):
            if until <= now:
                del self._gone[sid]
                self._owners.pop(sid, None)
        return len(idle)

    # ---------------------------------------------------------------------- state

    def count(self) -> int:
        return sum(1 for s in self._sessions.values() if s.alive)

    def memory(self) -> int:
        return sum(s.memory for s in self._sessions.values() if s.alive)

    def pids(self) -> dict[str, int]:
        """Session id -> process id (tests and diagnostics)."""
        return {s.id: s.proc.pid for s in self._sessions.values() if s.alive}

    def _get(self, session_id: str) -> _LocalSession:
        session = self._sessions.get(session_id)
        if session is not None and session.alive:
            return session
        gone = self._gone.get(session_id)
        if gone is not None:
            raise errors.SessionGoneError(session_id, gone[0])
        raise errors.SessionNotFoundError(session_id)

    def _bury(self, session: _LocalSession, reason: str) -> None:
        """Mark a session gone (for one more TTL)."""
        session.alive = False
        session.reason = session.reason or reason
        self._sessions.pop(session.id, None)
        self._gone[session.id] = (session.reason, time.monotonic() + self.policy.ttl)
        if session.pending is not None:
            settle(session.pending, exc=errors.SessionGoneError(session.id, session.reason))
        self._changed(session)

    def _record(self, session: _LocalSession) -> SessionRecord:
        expires = self.policy.ttl - (time.monotonic() - session.last_used)
        return SessionRecord(session.id, session.info, max(0.0, expires), session.memory,
                             session.solves, self.name)

    # --------------------------------------------------------------------- create

    def _spawn(self, session_id: str, spec: SessionSpec) -> WorkerProcess:
        main = functools.partial(
            _session_main, solve_timeout=self.policy.solve_timeout,
            refine_slice=self.policy.refine_slice)
        proc = WorkerProcess.spawn(main, self.policy.threads, f"ffs-session-{session_id[:8]}",
                                   self.start_method)
        try:
            proc.conn.send(spec)
        except BaseException:
            proc.kill()
            raise
        return proc

    def _admit(self, session_id: str, owner: str | None, estimate: int,
               max_per_owner: int | None = None) -> list[_LocalSession]:
        """Reserve room for session ``session_id`` of ``owner`` (:func:`admit_session`);
        the idle sessions that give way are buried here and returned, to be closed."""
        now = time.monotonic()
        slots = [SessionSlot(s.id, s.owner, s.memory,
                             None if s.lock.locked() else now - s.last_used)
                 for s in self._sessions.values() if s.alive]
        evicted = [self._sessions[sid] for sid in admit_session(
            [*slots, *self._reserved.values()], owner, estimate, self._limits(max_per_owner))]
        for session in evicted:
            self._bury(session, f"it gave way to a new session after "
                                f"{now - session.last_used:.0f} s without a drag (the open "
                                "sessions were at FFS_MAX_SESSIONS or FFS_MAX_SESSION_MEMORY; "
                                "FFS_SESSION_GIVE_WAY)")
        self._reserved[session_id] = SessionSlot(session_id, owner, estimate, None)
        return evicted

    def _limits(self, max_per_owner: int | None) -> Any:
        limits = self.policy.admission()
        if max_per_owner is None:
            return limits
        return dataclasses.replace(limits, max_per_owner=max_per_owner)

    async def create(self, spec: SessionSpec, owner: str | None = None,
                     max_per_owner: int | None = None) -> SessionRecord:
        await self.expire()
        estimate = estimate_memory(len(spec.vertices), len(spec.faces))
        session_id = uuid.uuid4().hex
        evicted = self._admit(session_id, owner, estimate, max_per_owner)
        proc: WorkerProcess | None = None
        try:
            await asyncio.gather(*(asyncio.to_thread(self._close, s) for s in evicted))
            try:
                proc = await asyncio.to_thread(self._spawn, session_id, spec)
            except OSError as exc:  # it died before it read the mesh
                raise errors.WorkerDiedError(f"the session process could not start or died at once "
                                      f"({exc})") from None
            message = await asyncio.to_thread(_wait_ready, proc, self.policy.setup_timeout)
            if message is None:
                raise errors.DeadlineError(f"the session was not ready within "
                                    f"{self.policy.setup_timeout:g} s (FFS_REQUEST_TIMEOUT)")
            if message[0] == "error":
                raise errors.TaskFailedError(message[1])
            _, info, memory = message
            session = _LocalSession(id=session_id, proc=proc, info=info,
                                    memory=int(memory) or estimate, owner=owner)
        except BaseException:
            self._reserved.pop(session_id, None)
            if proc is not None:
                await asyncio.to_thread(proc.kill)
            raise
        self._reserved.pop(session_id, None)
        used = self.memory()
        if used + session.memory > self.policy.max_memory:  # measured beyond the estimate
            await asyncio.to_thread(proc.kill)
            raise errors.SessionMemoryError(used, session.memory, self.policy.max_memory)
        self._sessions[session_id] = session
        self._owners[session_id] = owner
        proc.read(self._loop, lambda message: self._on_message(session, message),
                  lambda: self._on_exit(session), _unreadable,
                  f"ffs-session-reader-{session_id[:8]}")
        return self._record(session)

    # ---------------------------------------------------------------------- solve

    async def describe(self, session_id: str) -> SessionRecord:
        return self._record(self._get(session_id))

    async def owner(self, session_id: str) -> str | None:
        if session_id not in self._owners:
            raise errors.SessionNotFoundError(session_id)
        return self._owners[session_id]

    async def list(self, owner: str | None = None) -> list[SessionRecord]:
        return [self._record(s) for s in self._sessions.values()
                if s.alive and (owner is None or s.owner == owner)]

    async def shape(self, session_id: str) -> tuple[int, int]:
        info = self._get(session_id).info
        return len(info["handles"]), int(info["n_rotation_groups"])

    async def solve(self, session_id: str, positions: Any, rotations: Any,
                    fmt: str) -> DragAnswer:
        session = self._get(session_id)
        async with session.lock:
            if not session.alive:
                raise errors.SessionGoneError(session_id, session.reason or "closed")
            future = session.pending = new_future()
            try:
                session.proc.conn.send((positions, rotations, fmt))
                message = await asyncio.wait_for(asyncio.shield(future), self.policy.solve_timeout)
            except TimeoutError:  # (a subclass of OSError: first)
                self._bury(session, f"a solve took longer than {self.policy.solve_timeout:g} s "
                                    "(FFS_SESSION_SOLVE_TIMEOUT); the session was closed")
                await asyncio.to_thread(session.proc.kill)
                raise errors.DeadlineError(f"no result within {self.policy.solve_timeout:g} s "
                                    "(FFS_SESSION_SOLVE_TIMEOUT); the session was closed"
                                    ) from None
            except OSError:  # the process died before it read the drag: say how
                await asyncio.to_thread(session.proc.process.join, 2.0)
                if session.alive:  # (else the reader thread saw the exit first)
                    self.deaths += 1
                self._bury(session, self._death(session))
                raise errors.SessionGoneError(session_id, session.reason or "gone") from None
            finally:
                session.pending = None
            session.last_used = time.monotonic()
        if message[0] == "ok":
            _, body, timings, drag, refining = message
            session.solves += 1
            return DragAnswer(body, timings, drag, refining)
        raise errors.TaskFailedError(message[1])

    async def refined(self, session_id: str, drag: int, wait: float) -> Any:
        session = self._get(session_id)
        deadline = time.monotonic() + wait
        while True:
            if drag < 1 or drag > session.drag:
                raise errors.DragNotFoundError(session_id, drag, f"the session has answered "
                                                                 f"{session.drag} drags")
            if drag < session.drag:
                raise errors.DragSupersededError(session_id, drag, session.drag)
            if session.refined is not None and session.refined[0] == drag:
                result = session.refined[1]
                if isinstance(result, dict):
                    raise errors.TaskFailedError(result)
                return result
            if not session.refining:
                raise errors.DragNotFoundError(session_id, drag, "the session does not refine "
                                                                 "(open it with options.refine "
                                                                 "true)")
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(session.changed.wait(), left)
            if not session.alive:
                raise errors.SessionGoneError(session_id, session.reason or "closed")

    @staticmethod
    def _changed(session: _LocalSession) -> None:
        session.changed.set()
        session.changed = asyncio.Event()

    async def delete(self, session_id: str) -> None:
        if self._gone.pop(session_id, None) is not None:
            self._owners.pop(session_id, None)
            return
        session = self._sessions.get(session_id)
        if session is None:
            raise errors.SessionNotFoundError(session_id)
        session.closing = True
        self._sessions.pop(session_id, None)
        self._owners.pop(session_id, None)
        session.alive = False
        session.reason = "deleted"
        if session.pending is not None:
            settle(session.pending, exc=errors.SessionNotFoundError(session_id))
        self._changed(session)
        await asyncio.to_thread(self._close, session)

    # ------------------------------------------------------------ process plumbing

    def _on_message(self, session: _LocalSession, message: Message) -> None:
        if message[0] in ("refined", "refine-error"):  # unasked: a drag's refined shape
            drag = message[1].drag if message[0] == "refined" else message[1]
            if drag == session.drag:  # (else a newer drag's answer is on its way)
                session.refined = (drag, message[1] if message[0] == "refined"
                                   else message[2])
                session.refining = False
                self._changed(session)
            return
        if message[0] == "ok":  # (here, before a refined shape of this drag can arrive)
            session.drag, session.refining, session.refined = message[3], message[4], None
            self._changed(session)
        if session.pending is not None:
            settle(session.pending, result=message)

    def _on_exit(self, session: _LocalSession) -> None:
        if session.closing or not session.alive:
            return
        self.deaths += 1
        reason = self._death(session)
        logger.error("session %s: %s", session.id, reason)
        self._bury(session, reason)

    @staticmethod
    def _death(session: _LocalSession) -> str:
        return (f"its worker process died "
                f"({session.proc.exit_reason()})")

    @staticmethod
    def _close(session: _LocalSession) -> None:
        session.closing = True
        session.proc.close()


def _wait_ready(proc: WorkerProcess, timeout: float) -> Message | None:
    """The session process's first message (ready or error); None after ``timeout`` s."""
    try:
        if not proc.conn.poll(timeout):
            return None
        return proc.conn.recv()
    except (EOFError, OSError):
        proc.process.join(5.0)
        raise errors.WorkerDiedError(
            f"the session process died while it factorized "
            f"({proc.exit_reason()}); the mesh may be too large for the memory available"
        ) from None


def _unreadable(exc: Exception) -> Message:
    logger.error("unreadable session reply")
    return ("error", failure_of(exc))
