"""Process memory: give freed heap back to the system, measure what a process holds, and
keep the cyclic garbage collector out of the way while a body is parsed.

Used by the worker processes (between tasks) and by the HTTP process (after parsing a
large body in a thread)."""

from __future__ import annotations

import gc
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

RELEASE_ABOVE = 512 * 1024**2
"""Resident bytes beyond which a worker gives its freed heap back right after a task."""
IDLE_RELEASE = 1.0
"""Seconds without a next task after which a worker gives its freed heap back.

Giving memory back is not free: the next task faults every page in again, which on a VM
costs ~1 ms per MB (a 20K-face reconstruct: ~50 ms of a ~190 ms solve). So a busy worker
keeps a heap of up to :data:`RELEASE_ABOVE` from one task to the next, and an idle one
returns it."""


def release_memory() -> None:
    """Give freed heap memory back to the system (glibc ``malloc_trim``; a no-op elsewhere).

    Parsing a large JSON body allocates millions of small objects; once freed, glibc keeps
    the pages unless asked, so a process's RSS would stay at its largest body."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _malloc_trim() -> Any:
    """glibc's ``malloc_trim`` (loaded once), or None where there is none."""
    global _TRIM
    if _TRIM is None:
        import ctypes
        import ctypes.util

        try:
            _TRIM = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _TRIM = False
    return _TRIM or None


_TRIM: Any = None


def resident_memory() -> int:
    """Resident set size of this process in bytes (cheap: one read of ``/proc``)."""
    try:
        import psutil

        return int(psutil.Process().memory_info().rss)
    except Exception:
        return 0


def release_between_tasks(next_task_waiting: Any) -> None:
    """A worker's heap policy after a task.

    The freed heap (and the factor memory of idle PARDISO handles) goes back at once when
    the process holds more than :data:`RELEASE_ABOVE`, else only when no task came within
    :data:`IDLE_RELEASE` seconds.

    Args:
        next_task_waiting: called with :data:`IDLE_RELEASE`, says whether a task came
            meanwhile (e.g. ``Connection.poll``).
    """
    if resident_memory() > RELEASE_ABOVE or not next_task_waiting(IDLE_RELEASE):
        from solver.linalg import release_cached_factors

        release_cached_factors()  # the factor memory PARDISO's idle handles keep
        release_memory()


_later: list[Any] = []


def free_later(obj: Any) -> None:
    """Keep an object alive until :func:`free_deferred`, at most one at a time.

    Freeing the ~200 000 objects of a parsed 2 MB JSON body takes ~3 ms; a worker frees them
    after it has sent its answer instead of before. Any earlier object is freed here, so a
    process that never calls :func:`free_deferred` holds at most one.

    Args:
        obj: a parsed body.
    """
    _later[:] = [obj]


def free_deferred() -> None:
    """Free what :func:`free_later` kept (a worker calls this once its answer is sent)."""
    _later.clear()


_gc_lock = threading.Lock()
_gc_pauses = 0
_gc_was_enabled = False


@contextmanager
def gc_paused() -> Iterator[None]:
    """No cyclic garbage collection inside the block (nestable, any thread).

    Parsing a JSON body creates one list per row (60 000 for a 20K-face mesh); each few
    hundred of them trigger a collection that traverses every tracked object, which made
    parsing a 2 MB body 2-4x slower than orjson itself. Parsed bodies hold no cycles:
    refcounting frees them at the end of the block."""
    global _gc_pauses, _gc_was_enabled
    with _gc_lock:
        if _gc_pauses == 0:
            _gc_was_enabled = gc.isenabled()
            gc.disable()
        _gc_pauses += 1
    try:
        yield
    finally:
        with _gc_lock:
            _gc_pauses -= 1
            if _gc_pauses == 0 and _gc_was_enabled:
                gc.enable()


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


def machine_memory() -> int:
    """Bytes of memory this process's machine (or container) has: the physical memory, or
    the cgroup's limit where one is lower (cgroup v2 ``memory.max``, v1
    ``memory.limit_in_bytes``); 0 when unknown."""
    import os

    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 0
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as fh:
                text = fh.read().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < (total or int(text) + 1):
            total = int(text)
    return int(total)
