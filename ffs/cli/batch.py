"""Running a batch: every item ``-j`` at a time, in local worker processes (spawned, each
with its own :class:`ffs.local.Local`) or in threads (``-j 1``, or ``--server``: concurrent
jobs on the service), with progress events on one queue and ``--fail-fast``.

Progress: each item's reports go through the service's rule
(:class:`ffs_wire.progress.ProgressThrottle`: at most one per 0.2 s, a new stage, the first
and the last always), so a flattening that reports each of its thousands of charts does not
flood the queue from a worker process.

The files ``--align-to``, ``--cotangent``, ``--handles`` and ``--constraints`` name are read
once for the command (:func:`ffs.cli.items.check_given_files`); a local worker process gets
what they hold once, when it starts, not with every item.

``--fail-fast``: the worker whose item fails sets the stop event before it returns, so no
item starts after it (it is ``skipped``) and those still running stop at their next
progress report (``stopped``); the batch waits for nothing but the items already running
when the failure happened, at most ``jobs - 1``.
"""

from __future__ import annotations

import argparse
import concurrent.futures as futures
import multiprocessing
import os
import queue
import sys
import threading
import time
import traceback
from typing import Any

from ffs.cli.commands import RUNNERS
from ffs.cli.failures import StoppedError, describe_error, is_expected
from ffs.cli.items import Item, Row, skipped_row
from ffs.cli.progress import Display
from ffs_wire.progress import ProgressThrottle


def run_item(command: str, args: argparse.Namespace, item: Item, backend: Any,
             events: Any, stop: Any = None) -> Row:
    """Run one item.

    Args:
        command: The subcommand (a key of :data:`~ffs.cli.commands.RUNNERS`).
        args: The parsed command line.
        item: What to run.
        backend: :class:`ffs.local.Local` or :class:`ffs.client.Client`.
        events: A queue that gets ``(index, stage, fraction)`` progress events.
        stop: A ``threading.Event`` or ``multiprocessing.Event`` of the batch: set, an item
            does not start and a running one stops at its next progress report; set here
            when the item fails and ``--fail-fast`` is on.

    Returns:
        The item's row; failures included (it never raises for bad input).
    """
    if stop is not None and stop.is_set():
        return skipped_row(item)
    row = Row(file=item.name, outputs=item.outputs, path=" + ".join(item.inputs),
              pid=os.getpid(), started=time.time())
    events.put((item.index, "start", 0.0))
    throttle = ProgressThrottle(lambda stage, fraction, detail=None: events.put(
        (item.index, stage, float(fraction))))

    def progress(stage: str, fraction: float) -> None:
        if stop is not None and stop.is_set():
            raise StoppedError("stopped")
        throttle(stage, fraction)

    clock = time.perf_counter()
    try:
        RUNNERS[command](backend, item, args, progress, row)
    except StoppedError:
        row.status, row.error = "stopped", "stopped before it finished"
    except Exception as exc:
        row.status, row.error = "failed", describe_error(exc)
        for path in item.inputs:  # the line starts with the file already
            row.error = row.error.removeprefix(f"{path}: ")
        if args.verbose and not is_expected(exc):
            row.extra["traceback"] = traceback.format_exc()
        if args.fail_fast and stop is not None:
            stop.set()
    throttle.flush()  # the last report held back, before the item is done
    row.seconds = time.perf_counter() - clock
    row.finished = time.time()
    return row


# --------------------------------------------------------------------- process pool

_WORKER: dict[str, Any] = {}
"""A local worker process's ``events`` queue, ``stop`` event, ``backend`` and ``given``
(what the option files hold, :func:`ffs.cli.items.check_given_files`)."""


def _init_worker(events: Any, stop: Any, given: dict[str, Any] | None = None) -> None:
    """Set up a local worker process: progress goes to ``events``; Ctrl-C is the parent's;
    ``given`` (the option files, read once by the command) arrives here once, not with
    every item."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _WORKER["events"], _WORKER["stop"], _WORKER["given"] = events, stop, given
    from ffs.local import Local

    _WORKER["backend"] = Local()


def _worker_run(command: str, args: argparse.Namespace, item: Item) -> Row:
    args.given = _WORKER["given"]
    return run_item(command, args, item, _WORKER["backend"], _WORKER["events"],
                    _WORKER["stop"])


# --------------------------------------------------------------------------- batch


def _backend(args: argparse.Namespace) -> Any:
    """The backend of the threads: a client of ``--server``, or the library in-process."""
    if args.server:
        from ffs.client import Client

        return Client(args.server, timeout=args.timeout, token=args.token)
    from ffs.local import Local

    return Local()


def run_batch(command: str, args: argparse.Namespace, items: list[Item]) -> list[Row]:
    """Run every item, ``args.jobs`` at a time, with progress bars.

    Args:
        command: The subcommand.
        args: The parsed command line (``jobs``, ``server``, ``fail_fast``, ``quiet``, ...).
        items: What to run.

    Returns:
        One row per item, in input order.

    Raises:
        KeyboardInterrupt: Ctrl-C; running jobs on a server are cancelled at their next
            poll, local workers are terminated.
    """
    display = Display(sys.stderr.isatty() and not args.quiet, len(items))
    for item in items:
        display.name(item.index, item.name)
    rows: dict[int, Row] = {}
    stop: Any
    pool: futures.Executor
    if args.server or args.jobs == 1:
        events: Any = queue.Queue()
        stop = threading.Event()
        backend = _backend(args)
        pool = futures.ThreadPoolExecutor(max_workers=args.jobs)
        pending = {pool.submit(run_item, command, args, item, backend, events, stop): item
                   for item in items}
    else:
        context = multiprocessing.get_context("spawn")
        events, stop = context.Queue(), context.Event()
        given = getattr(args, "given", None)
        pool = futures.ProcessPoolExecutor(max_workers=args.jobs, mp_context=context,
                                           initializer=_init_worker,
                                           initargs=(events, stop, given))
        shipped = argparse.Namespace(**{**vars(args), "given": None})  # given: once a worker
        pending = {pool.submit(_worker_run, command, shipped, item): item for item in items}
    try:
        while pending:
            done, _ = futures.wait(pending, timeout=0.05, return_when=futures.FIRST_COMPLETED)
            _drain(events, display)
            for future in done:
                item = pending.pop(future)
                rows[item.index] = _row_of(future, item)
                display.done(item.index)
                if rows[item.index].status == "failed" and args.fail_fast:
                    stop.set()  # already, unless the worker process died
            if stop.is_set():  # what has not started is not run
                for future in [f for f in pending if f.cancel()]:
                    cancelled = pending.pop(future)
                    rows[cancelled.index] = skipped_row(cancelled)
        _drain(events, display)
    except KeyboardInterrupt:
        stop.set()  # jobs on a server notice it at their next poll and are cancelled
        display.close()
        pool.shutdown(wait=False, cancel_futures=True)
        for process in list((getattr(pool, "_processes", None) or {}).values()):
            process.terminate()  # local workers: their solves are of no use any more
        futures.wait(pending, timeout=5)
        raise
    finally:
        display.close()
    pool.shutdown(wait=True)
    return [rows[item.index] for item in items]


def _row_of(future: futures.Future[Row], item: Item) -> Row:
    """The row a finished future holds (a cancelled one: skipped; a dead worker: failed)."""
    try:
        return future.result()
    except futures.CancelledError:
        return skipped_row(item)
    except Exception as exc:  # a worker process that died (killed, out of memory)
        return Row(item.name, item.outputs, status="failed",
                   error=f"the worker running it failed: {describe_error(exc)}")


def _drain(events: Any, display: Display) -> None:
    """Pass every queued progress event to the display."""
    while True:
        try:
            index, stage, fraction = events.get_nowait()
        except queue.Empty:
            return
        display.event(index, stage, fraction)
