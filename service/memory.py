"""Process memory: give freed heap back to the system, and measure what a process holds.

Used by the worker processes (after each task) and by the HTTP process (after parsing a
large body in a thread)."""

from __future__ import annotations

from typing import Any


def release_memory() -> None:
    """Give freed heap memory back to the system (glibc ``malloc_trim``; a no-op elsewhere).

    Parsing a large JSON body allocates millions of small objects; once freed, glibc keeps
    the pages unless asked, so a process's RSS would stay at its largest body."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _malloc_trim() -> Any:
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
