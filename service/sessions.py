"""Interactive deformation sessions: a prefactorized :class:`solver.Deformer` kept warm.

``POST /v1/sessions`` factorizes the rest mesh's system once; every drag
(``POST /v1/sessions/{id}/solve`` or a WebSocket message) only back-substitutes. The
factorization lives with exactly one worker:

* local executor (:class:`LocalSessions`): one dedicated process per session, outside the
  stateless task pool, driven over its own pipe. A crash, an OOM kill or a solve beyond
  ``FFS_SESSION_SOLVE_TIMEOUT`` ends only that session, which then answers 410;
* Dask (:class:`service.cluster.DaskSessions`): a Dask actor pinned to one worker.

Both run :class:`SessionState` where the factorization lives. Admission is bounded by
``FFS_MAX_SESSIONS`` (429 beyond) and ``FFS_MAX_SESSION_MEMORY`` (503 beyond): before a
session is built its memory is estimated from the face count (:func:`estimate_memory`);
once built it is measured (the private memory, USS, of its process) and that number
counts from then on. Idle sessions close after ``FFS_SESSION_TTL`` seconds; a session that
expired or whose worker died answers 410 ``session-gone`` for another TTL, then 404.

Wire formats (also in docs/service.md):

* a drag in JSON: ``{"handle_positions": [[x, y, z], ...], "handle_rotations"?: [3x3, ...],
  "seq"?: n}``;
* a drag in binary: little-endian float32, ``3 h`` values (h handle positions) optionally
  followed by ``9 g`` values (g row-major rotations, re-orthonormalized on arrival);
* the vertices in binary (``application/octet-stream``): little-endian float32, ``3 n``
  values; WebSocket replies put an 8-byte header in front: uint32 ``seq``, uint32 ``n``
  (both little-endian).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import multiprocessing
import signal
import struct
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Protocol

import numpy as np

from service.executor import post_threadsafe, prepare_worker_process
from service.problems import ProblemError, from_worker_error

logger = logging.getLogger("service.sessions")

SESSION_FORMATS: tuple[str, ...] = ("json", "glb", "gltf", "f32")
"""Response formats of a session solve, in server preference order."""
WS_HEADER = struct.Struct("<II")
"""WebSocket reply header: uint32 seq, uint32 vertex count (little-endian)."""
BYTES_PER_FACE_ESTIMATE = 6_000
"""Admission estimate of a session's memory per face before it is measured (a 20K-face
session measures about 180 MiB with PARDISO, its process included)."""
BASE_MEMORY_ESTIMATE = 80 * 1024**2
"""Admission estimate of a session process's own memory."""
MAX_MAGNITUDE = 1e60


def estimate_memory(n_vertices: int, n_faces: int) -> int:
    """Bytes a session of this size is expected to hold (used before it is measured)."""
    return int(BASE_MEMORY_ESTIMATE + BYTES_PER_FACE_ESTIMATE * max(n_faces, 1))


# -------------------------------------------------------------------------- worker side


def process_memory() -> int:
    """Private memory (USS) of this process in bytes, RSS where USS is unavailable."""
    try:
        import psutil

        proc = psutil.Process()
        try:
            return int(proc.memory_full_info().uss)
        except (psutil.AccessDenied, AttributeError, OSError):
            return int(proc.memory_info().rss)
    except Exception:
        return 0


def encode_vertices(vertices: np.ndarray, faces: np.ndarray, fmt: str) -> bytes:
    """The body of a solve in format ``fmt`` (see :data:`SESSION_FORMATS`)."""
    from service import output

    if fmt == "f32":
        return np.ascontiguousarray(vertices, dtype="<f4").tobytes()
    if fmt == "json":
        return output.json_bytes({"vertices": vertices})
    if fmt == "f64":  # not offered over HTTP; exact float64 for tests
        return np.ascontiguousarray(vertices, dtype="<f8").tobytes()
    return output.mesh_bytes(fmt, vertices, faces)


class SessionState:
    """The warm side of a session: one :class:`solver.Deformer` (factorized at init).

    ``spec``: ``{"vertices" (n, 3), "faces" (m, 3), "handles" (h,), "rotations": [face
    index arrays], "roi": (k,) | None, "options": {frame_weight, orthonormalize,
    orthonormal_weight, weighting, solver}, "backend": default backend}``.
    """

    def __init__(self, spec: dict[str, Any]) -> None:
        import solver

        options = spec.get("options") or {}
        groups = [np.asarray(g, dtype=np.int64) for g in spec.get("rotations") or []]
        start = time.perf_counter()
        self.deformer = solver.Deformer(
            spec["vertices"], spec["faces"], np.asarray(spec["handles"], dtype=np.int64),
            rotation_handles=groups or None,
            roi=None if spec.get("roi") is None else np.asarray(spec["roi"], dtype=np.int64),
            frame_weight=options.get("frame_weight", 1000.0),
            orthonormalize=options.get("orthonormalize", False),
            orthonormal_weight=options.get("orthonormal_weight", 1000.0),
            weighting=options.get("weighting", "uniform"),
            backend=options.get("solver") or spec.get("backend", "auto"),
            refine=bool(options.get("refine")))  # null: off (a refined drag costs more)
        # A first solve at rest checks the factorization (and warms the backend up).
        self.deformer.solve()
        self.setup_seconds = time.perf_counter() - start
        self.faces = self.deformer.faces
        self.solves = 0

    def info(self) -> dict[str, Any]:
        d = self.deformer
        return {"n_vertices": len(d.rest), "n_faces": len(d.faces),
                "handles": [int(h) for h in d.handles], "n_rotation_groups": d.n_groups,
                "setup_seconds": self.setup_seconds, "backend": d.backend}

    def solve(self, positions: np.ndarray, rotations: np.ndarray | None,
              fmt: str) -> tuple[bytes, dict[str, float]]:
        """Deformed vertices for new handle targets, encoded; and stage timings."""
        t0 = time.perf_counter()
        vertices = self.deformer.solve(positions, rotations)
        t1 = time.perf_counter()
        body = encode_vertices(vertices, self.faces, fmt)
        self.solves += 1
        return body, {"solve": t1 - t0, "encode": time.perf_counter() - t1}


def _session_main(conn: Connection, threads: int) -> None:
    """Entry point of a local session process: build the session, then serve solves."""
    prepare_worker_process(threads)
    from service import tasks

    tasks.initialize_worker(threads)
    try:
        spec = conn.recv()
        try:
            state = SessionState(spec)
        except Exception as exc:
            conn.send(("error", tasks.describe_error(exc)))
            return
        del spec
        conn.send(("ready", state.info(), process_memory()))
        while True:
            message = conn.recv()
            if message is None:
                return
            _, positions, rotations, fmt = message
            try:
                body, timings = state.solve(positions, rotations, fmt)
            except Exception as exc:
                conn.send(("error", tasks.describe_error(exc)))
            else:
                conn.send(("ok", body, timings))
    except (EOFError, OSError):  # the service went away
        return


# ---------------------------------------------------------------------------- protocol


class SessionBackend(Protocol):
    """What the session routes need (local processes or Dask actors)."""

    name: str

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def create(self, spec: dict[str, Any]) -> dict[str, Any]:
        """Build a session; its document (201 body). 429/503/422/504 problems."""

    async def describe(self, session_id: str) -> dict[str, Any]:
        """The session document; 404 unknown, 410 expired or its worker died."""

    async def shape(self, session_id: str) -> tuple[int, int]:
        """(handles, rotation groups) of a session; 404/410 like :meth:`describe`."""

    async def solve(self, session_id: str, positions: np.ndarray,
                    rotations: np.ndarray | None, fmt: str) -> tuple[bytes, dict[str, float]]:
        """One drag: (encoded vertices, timings); 404/410/422/504 problems."""

    async def delete(self, session_id: str) -> None:
        """Close a session (404 if unknown; a gone one is forgotten)."""

    def count(self) -> int:
        """Live sessions (as last seen)."""

    def memory(self) -> int:
        """Bytes held by live sessions (as last seen)."""


def gone_problem(session_id: str, reason: str) -> ProblemError:
    return ProblemError("session-gone", f"session {session_id} is gone: {reason}; create a "
                        "new one", reason=reason)


def not_found(session_id: str) -> ProblemError:
    return ProblemError("not-found", f"no session {session_id!r} (it may have been deleted, "
                        "or it expired long ago)")


def too_many(count: int, limit: int, retry_after: int) -> ProblemError:
    return ProblemError("too-many-sessions",
                        f"{count} sessions are open (limit {limit}, FFS_MAX_SESSIONS); delete "
                        "one or wait until an idle one expires",
                        headers={"Retry-After": str(retry_after)}, limit=limit, count=count,
                        retry_after=retry_after)


def memory_problem(used: int, needed: int, limit: int) -> ProblemError:
    return ProblemError("session-memory",
                        f"sessions hold {used / 2**20:.0f} MiB and this one needs about "
                        f"{needed / 2**20:.0f} MiB more; the limit is {limit / 2**20:.0f} MiB "
                        "(FFS_MAX_SESSION_MEMORY)", headers={"Retry-After": "30"},
                        memory_used=used, memory_needed=needed, memory_limit=limit)


def session_document(session_id: str, info: dict[str, Any], *, expires_in: float,
                     backend: str, memory: int, solves: int) -> dict[str, Any]:
    """The 201 body of ``POST /v1/sessions`` and the body of ``GET /v1/sessions/{id}``."""
    base = f"/v1/sessions/{session_id}"
    return {"id": session_id, "n_vertices": info["n_vertices"], "n_faces": info["n_faces"],
            "handles": info["handles"], "n_rotation_groups": info["n_rotation_groups"],
            "expires_in": round(max(0.0, expires_in), 3),
            "setup_seconds": round(info["setup_seconds"], 6), "backend": info["backend"],
            "executor": backend, "memory_bytes": int(memory), "solves": int(solves),
            "links": {"self": base, "solve": f"{base}/solve", "ws": f"{base}/ws"}}


# ------------------------------------------------------------------------ wire formats


def _bad(field: str, reason: str, index: int | None = None) -> ProblemError:
    return ProblemError("validation-error", f"{field}: {reason}",
                        errors=[{"field": field, "index": index, "reason": reason}])


def _check_finite(values: np.ndarray, field: str) -> None:
    bad = ~np.isfinite(values) | (np.abs(values) > MAX_MAGNITUDE)
    if bad.any():
        row = int(np.argwhere(bad)[0][0])
        raise _bad(field, "not a finite number within +-1e60", row)


def parse_drag_binary(data: bytes, n_handles: int,
                      n_groups: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Positions (h, 3) and rotations (g, 3, 3) | None from a binary drag."""
    if len(data) % 4:
        raise _bad("body", f"{len(data)} bytes is not a whole number of float32 values")
    values = np.frombuffer(data, dtype="<f4").astype(np.float64)
    n_pos = 3 * n_handles
    if len(values) == n_pos:
        rotations = None
    elif n_groups and len(values) == n_pos + 9 * n_groups:
        from solver.rotations import is_rotation, nearest_rotation

        rotations = values[n_pos:].reshape(n_groups, 3, 3)
        _check_finite(rotations.reshape(n_groups, 9), "handle_rotations")
        near = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2))
        close = (near <= 1e-4) & (np.linalg.det(rotations) > 0)
        rotations = np.where(close[:, None, None], nearest_rotation(rotations), rotations)
        bad = np.flatnonzero(~is_rotation(rotations))
        if len(bad):
            raise _bad("handle_rotations", "not a rotation matrix (orthonormal with det +1)",
                       int(bad[0]))
    else:
        expected = f"{n_pos}" + (f" or {n_pos + 9 * n_groups}" if n_groups else "")
        raise _bad("body", f"expected {expected} little-endian float32 values "
                           f"({n_handles} handle positions"
                           + (f", then {n_groups} row-major 3x3 rotations" if n_groups else "")
                           + f"), got {len(values)}")
    positions = values[:n_pos].reshape(n_handles, 3)
    _check_finite(positions, "handle_positions")
    return positions, rotations


def parse_drag_json(doc: Any, n_handles: int,
                    n_groups: int) -> tuple[np.ndarray, np.ndarray | None, int | None]:
    """Positions, rotations and the optional ``seq`` of a JSON drag (already parsed)."""
    from service.inputs import validate_object
    from service.schemas import SessionDrag

    model = validate_object(SessionDrag, doc)
    positions = np.asarray(model.handle_positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) != n_handles:
        raise _bad("handle_positions", f"expected {n_handles} positions (one per handle), "
                                       f"got {len(positions)}")
    rotations = None
    if model.handle_rotations is not None:
        rotations = np.asarray(model.handle_rotations, dtype=np.float64).reshape(-1, 3, 3)
        if len(rotations) != n_groups:
            raise _bad("handle_rotations", f"expected {n_groups} rotations (one per rotation "
                                           f"group), got {len(rotations)}")
    return positions, rotations, model.seq


def ws_reply(seq: int, body: bytes) -> bytes:
    """A WebSocket reply: header (uint32 seq, uint32 n) + float32 vertices."""
    return WS_HEADER.pack(seq & 0xFFFFFFFF, len(body) // 12) + body


# ------------------------------------------------------------------- local processes


@dataclass
class _LocalSession:
    id: str
    process: Any
    conn: Connection
    info: dict[str, Any]
    memory: int
    last_used: float = field(default_factory=time.monotonic)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    pending: asyncio.Future[Any] | None = None
    alive: bool = True
    closing: bool = False
    reason: str | None = None
    solves: int = 0


class LocalSessions:
    """One dedicated process per session (see the module docstring)."""

    name = "local"

    def __init__(self, *, ttl: float, max_sessions: int, max_memory: int, threads: int,
                 solve_timeout: float, setup_timeout: float,
                 start_method: str = "forkserver") -> None:
        self.ttl = ttl
        self.max_sessions = max_sessions
        self.max_memory = max_memory
        self.threads = threads
        self.solve_timeout = solve_timeout
        self.setup_timeout = setup_timeout
        self.start_method = start_method
        self._sessions: dict[str, _LocalSession] = {}
        self._gone: dict[str, tuple[str, float]] = {}
        self._reserved: dict[str, int] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._sweeper: asyncio.Task[None] | None = None
        self.deaths = 0

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._sweeper = asyncio.create_task(self._sweep())

    async def stop(self) -> None:
        if self._sweeper is not None:
            self._sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._sweeper
        sessions = list(self._sessions.values())
        self._sessions.clear()
        await asyncio.gather(*(asyncio.to_thread(self._close_process, s) for s in sessions))

    async def _sweep(self) -> None:
        interval = max(0.05, min(10.0, self.ttl / 4))
        while True:
            await asyncio.sleep(interval)
            try:
                await self.expire()
            except Exception:
                logger.exception("session sweeper failed")

    async def expire(self) -> int:
        """Close sessions idle for longer than the TTL; drop old tombstones."""
        now = time.monotonic()
        idle = [s for s in self._sessions.values()
                if s.alive and not s.lock.locked() and now - s.last_used > self.ttl]
        for s in idle:
            self._bury(s, f"it expired after {self.ttl:g} s without a solve (FFS_SESSION_TTL)")
            await asyncio.to_thread(self._close_process, s)
        for sid, (_, until) in list(self._gone.items()):
            if until <= now:
                del self._gone[sid]
        return len(idle)

    # ---------------------------------------------------------------------- state

    def count(self) -> int:
        return sum(1 for s in self._sessions.values() if s.alive)

    def memory(self) -> int:
        return sum(s.memory for s in self._sessions.values() if s.alive)

    def pids(self) -> dict[str, int]:
        """Session id -> process id (tests and diagnostics)."""
        return {s.id: s.process.pid for s in self._sessions.values() if s.alive}

    def _get(self, session_id: str) -> _LocalSession:
        session = self._sessions.get(session_id)
        if session is not None and session.alive:
            return session
        gone = self._gone.get(session_id)
        if gone is not None:
            raise gone_problem(session_id, gone[0])
        raise not_found(session_id)

    def _bury(self, session: _LocalSession, reason: str) -> None:
        """Mark a session gone (410 for one more TTL)."""
        session.alive = False
        session.reason = session.reason or reason
        self._sessions.pop(session.id, None)
        self._gone[session.id] = (session.reason, time.monotonic() + self.ttl)
        if session.pending is not None and not session.pending.done():
            session.pending.set_exception(gone_problem(session.id, session.reason))

    def _document(self, session: _LocalSession) -> dict[str, Any]:
        expires = self.ttl - (time.monotonic() - session.last_used)
        return session_document(session.id, session.info, expires_in=expires,
                                backend=self.name, memory=session.memory,
                                solves=session.solves)

    # --------------------------------------------------------------------- create

    def _context(self) -> Any:
        ctx = multiprocessing.get_context(self.start_method)
        if self.start_method == "forkserver":
            ctx.set_forkserver_preload(["service.tasks"])
        return ctx

    def _spawn(self, session_id: str, spec: dict[str, Any]) -> tuple[Any, Connection]:
        ctx = self._context()
        parent, child = ctx.Pipe(duplex=True)
        process = ctx.Process(target=_session_main, args=(child, self.threads),
                              name=f"ffs-session-{session_id[:8]}", daemon=True)
        process.start()
        child.close()
        try:
            parent.send(spec)
        except BaseException:
            _kill(process, parent)
            raise
        return process, parent

    @staticmethod
    def _wait_ready(conn: Connection, timeout: float) -> tuple[Any, ...] | None:
        if not conn.poll(timeout):
            return None
        return conn.recv()

    def _admit(self, estimate: int) -> None:
        open_now = self.count() + len(self._reserved)
        if open_now >= self.max_sessions:
            raise too_many(open_now, self.max_sessions,
                           max(1, min(120, math.ceil(self.ttl / 4))))
        used = self.memory() + sum(self._reserved.values())
        if used + estimate > self.max_memory:
            raise memory_problem(used, estimate, self.max_memory)

    async def create(self, spec: dict[str, Any]) -> dict[str, Any]:
        await self.expire()
        estimate = estimate_memory(len(spec["vertices"]), len(spec["faces"]))
        self._admit(estimate)
        session_id = uuid.uuid4().hex
        self._reserved[session_id] = estimate
        process = conn = None
        try:
            try:
                process, conn = await asyncio.to_thread(self._spawn, session_id, spec)
            except OSError as exc:  # it died before it read the mesh
                raise ProblemError("worker-died", f"the session process could not start or "
                                   f"died at once ({exc})") from None
            try:
                message = await asyncio.to_thread(self._wait_ready, conn, self.setup_timeout)
            except (EOFError, OSError):
                process.join(5.0)
                raise ProblemError(
                    "worker-died", f"the session process (pid {process.pid}) died while it "
                    f"factorized ({_exit_reason(process.exitcode)}); the mesh may be too large "
                    "for the memory available") from None
            if message is None:
                raise ProblemError("timeout", f"the session was not ready within "
                                   f"{self.setup_timeout:g} s (FFS_REQUEST_TIMEOUT)")
            if message[0] == "error":
                raise from_worker_error(message[1])
            _, info, memory = message
            session = _LocalSession(id=session_id, process=process, conn=conn, info=info,
                                    memory=int(memory) or estimate)
        except BaseException:
            self._reserved.pop(session_id, None)
            if process is not None:
                await asyncio.to_thread(_kill, process, conn)
            raise
        self._reserved.pop(session_id, None)
        used = self.memory()
        if used + session.memory > self.max_memory:  # measured beyond the estimate
            await asyncio.to_thread(_kill, process, conn)
            raise memory_problem(used, session.memory, self.max_memory)
        self._sessions[session_id] = session
        threading.Thread(target=self._reader, args=(session,), daemon=True,
                         name=f"ffs-session-reader-{session_id[:8]}").start()
        return self._document(session)

    # ---------------------------------------------------------------------- solve

    async def describe(self, session_id: str) -> dict[str, Any]:
        return self._document(self._get(session_id))

    async def shape(self, session_id: str) -> tuple[int, int]:
        info = self._get(session_id).info
        return len(info["handles"]), int(info["n_rotation_groups"])

    async def solve(self, session_id: str, positions: np.ndarray,
                    rotations: np.ndarray | None, fmt: str) -> tuple[bytes, dict[str, float]]:
        session = self._get(session_id)
        assert self._loop is not None
        async with session.lock:
            if not session.alive:
                raise gone_problem(session_id, session.reason or "closed")
            future = self._loop.create_future()
            future.add_done_callback(_consume)
            session.pending = future
            try:
                session.conn.send(("solve", positions, rotations, fmt))
                message = await asyncio.wait_for(asyncio.shield(future), self.solve_timeout)
            except TimeoutError:  # (a subclass of OSError: first)
                self._bury(session, f"a solve took longer than {self.solve_timeout:g} s "
                                    "(FFS_SESSION_SOLVE_TIMEOUT); the session was closed")
                await asyncio.to_thread(_kill, session.process, session.conn)
                raise ProblemError("timeout", f"no result within {self.solve_timeout:g} s "
                                   "(FFS_SESSION_SOLVE_TIMEOUT); the session was closed"
                                   ) from None
            except OSError:
                self._bury(session, "its process is gone")
                raise gone_problem(session_id, session.reason or "gone") from None
            finally:
                session.pending = None
            session.last_used = time.monotonic()
        if message[0] == "ok":
            session.solves += 1
            return message[1], message[2]
        raise from_worker_error(message[1])

    async def delete(self, session_id: str) -> None:
        if self._gone.pop(session_id, None) is not None:
            return
        session = self._sessions.get(session_id)
        if session is None:
            raise not_found(session_id)
        session.closing = True
        self._sessions.pop(session_id, None)
        session.alive = False
        session.reason = "deleted"
        if session.pending is not None and not session.pending.done():
            session.pending.set_exception(not_found(session_id))
        await asyncio.to_thread(self._close_process, session)

    # ------------------------------------------------------------ process plumbing

    def _reader(self, session: _LocalSession) -> None:
        """Thread: forward the replies of one session process to the event loop."""
        while True:
            try:
                message = session.conn.recv()
            except (EOFError, OSError):
                break
            except Exception as exc:  # a reply that cannot be unpickled
                message = ("error", {"category": "internal", "exception": type(exc).__name__,
                                     "message": f"unreadable session reply: {exc}"})
            if not self._post(self._on_message, session, message):
                return
        session.process.join(5.0)
        self._post(self._on_exit, session)

    def _post(self, fn: Callable[..., None], *args: Any) -> bool:
        return post_threadsafe(self._loop, fn, *args)

    @staticmethod
    def _on_message(session: _LocalSession, message: tuple[Any, ...]) -> None:
        future = session.pending
        if future is not None and not future.done():
            future.set_result(message)

    def _on_exit(self, session: _LocalSession) -> None:
        if session.closing or not session.alive:
            return
        self.deaths += 1
        reason = (f"its worker process (pid {session.process.pid}) died "
                  f"({_exit_reason(session.process.exitcode)})")
        logger.error("session %s: %s", session.id, reason)
        self._bury(session, reason)

    @staticmethod
    def _close_process(session: _LocalSession) -> None:
        session.closing = True
        with contextlib.suppress(Exception):
            session.conn.send(None)
        session.process.join(2.0)
        _kill(session.process, session.conn)


def _consume(future: asyncio.Future[Any]) -> None:
    """Mark a future's exception as retrieved (a solve may stop waiting for it)."""
    if not future.cancelled():
        future.exception()


def _kill(process: Any, conn: Connection | None) -> None:
    if process.is_alive():
        with contextlib.suppress(Exception):
            process.kill()
        process.join(2.0)
    if conn is not None:
        with contextlib.suppress(Exception):
            conn.close()


def _exit_reason(code: int | None) -> str:
    if code is not None and code < 0 and -code in signal.Signals._value2member_map_:
        return f"killed by signal {signal.Signals(-code).name}"
    return f"exit code {code}"


def make_sessions(settings: Any) -> SessionBackend:
    """The session backend of the local executor (the Dask one lives in service.cluster)."""
    return LocalSessions(ttl=settings.session_ttl, max_sessions=settings.max_sessions,
                         max_memory=settings.max_session_memory,
                         threads=settings.effective_session_threads,
                         solve_timeout=settings.session_solve_timeout,
                         setup_timeout=settings.request_timeout,
                         start_method=settings.start_method)
