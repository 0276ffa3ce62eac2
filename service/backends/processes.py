"""One worker process of this service: started with its own duplex pipe, read by a thread.

The local pool's workers (:mod:`service.backends.local.executor`) and the local session
processes (:mod:`service.backends.local.sessions`) are both a :class:`WorkerProcess`: a
``forkserver`` (or ``spawn``) child running ``target(conn, threads)``, a reader thread in
this process that posts every message to the event loop, and the same exit reasons and kill.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from service.backends.loops import post_threadsafe
from solver.mesh.io import READER_MODULES

PRELOAD = ["service.operations", *READER_MODULES]
"""Modules the forkserver imports once, so that each new worker starts warm (the file
readers' deferred imports, :data:`solver.mesh.io.READER_MODULES`)."""

Message = tuple[Any, ...]


@dataclass
class WorkerProcess:
    """A started child process and the parent's end of its pipe."""

    process: Any
    conn: Connection

    @classmethod
    def spawn(cls, target: Callable[[Connection, int], None], threads: int, name: str,
              start_method: str = "forkserver") -> WorkerProcess:
        """Start ``target(child_conn, threads)`` in a new process (blocking: run it in a
        thread).

        Args:
            target: the process's main function.
            threads: the compute threads it may use.
            name: the process's name.
            start_method: ``"forkserver"`` (preloading :data:`PRELOAD`) or ``"spawn"``.

        Returns:
            The started :class:`WorkerProcess`.
        """
        ctx = multiprocessing.get_context(start_method)
        if start_method == "forkserver":
            ctx.set_forkserver_preload(PRELOAD)
        parent, child = ctx.Pipe(duplex=True)
        process = ctx.Process(target=target, args=(child, threads), name=name, daemon=True)
        process.start()
        child.close()
        return cls(process, parent)

    @property
    def pid(self) -> int | None:
        """The child's process id (None before it started)."""
        return self.process.pid

    def read(self, loop: asyncio.AbstractEventLoop | None,
             on_message: Callable[[Message], None], on_exit: Callable[[], None],
             unreadable: Callable[[Exception], Message], name: str) -> None:
        """Start the thread that reads the pipe.

        Args:
            loop: the event loop the callbacks run on.
            on_message: called with each message.
            on_exit: called once at the end of the pipe (the process exited).
            unreadable: turns the exception of a message that cannot be unpickled into the
                message ``on_message`` gets instead.
            name: the thread's name.
        """

        def reader() -> None:
            while True:
                try:
                    message = self.conn.recv()
                except (EOFError, OSError):
                    break
                except Exception as exc:  # a reply that cannot be unpickled
                    message = unreadable(exc)
                if not post_threadsafe(loop, on_message, message):
                    return
            self.process.join(5.0)
            post_threadsafe(loop, on_exit)

        threading.Thread(target=reader, daemon=True, name=name).start()

    def exit_reason(self) -> str:
        """``killed by signal SIGKILL`` or ``exit code N``."""
        code = self.process.exitcode
        if code is not None and code < 0 and -code in signal.Signals._value2member_map_:
            return f"killed by signal {signal.Signals(-code).name}"
        return f"exit code {code}"

    def kill(self) -> None:
        """Kill the process (if alive) and close the pipe (blocking, at most ~2 s)."""
        if self.process.is_alive():
            with contextlib.suppress(Exception):
                self.process.kill()
            self.process.join(2.0)
        with contextlib.suppress(Exception):
            self.conn.close()

    def close(self, grace: float = 2.0) -> None:
        """Ask the process to stop (``None`` on the pipe), then kill it.

        Args:
            grace: seconds to wait for it to exit by itself.
        """
        with contextlib.suppress(Exception):
            self.conn.send(None)
        self.process.join(grace)
        self.kill()
