"""Keep freed memory in the process, so that numpy's temporaries do not page-fault.

Every residual evaluation of the refinement allocates a few dozen temporaries of 0.1-3 MB
(one float64 per hinge or edge: 240 KB at 20K faces). glibc's ``malloc`` serves blocks
above its mmap threshold from fresh ``mmap`` pages and hands the top of the heap back to
the kernel once more than its trim threshold is free; both thresholds start at 128 KB and
adapt only up to the size of the last freed block. A function that frees its temporaries
on return therefore gives their pages back, and the next call takes a page fault and a
kernel zero-fill for every 4 KB it touches: on the rocker-arm (30K hinges) the dihedral
angles took 10 ms instead of 3.3 ms, their gradients 16 ms instead of 6.4 ms
(docs/refinement.md, "Memory allocation").

:func:`retain_freed_memory` fixes both thresholds (``mallopt``), which keeps up to
``trim_bytes`` of freed heap for reuse; it runs when :mod:`solver` is imported. A process
that sets glibc's own tunables (``MALLOC_TRIM_THRESHOLD_``, ``MALLOC_MMAP_THRESHOLD_``,
``GLIBC_TUNABLES``) keeps them; other C libraries (musl, macOS, Windows) are left alone.
"""

from __future__ import annotations

import ctypes
import os
import sys

MMAP_THRESHOLD = 32 * 2**20
"""Blocks above this come from ``mmap`` (glibc's largest adaptive threshold on 64 bits)."""
TRIM_THRESHOLD = 256 * 2**20
"""Freed memory kept at the top of the heap before it is returned to the kernel."""
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
_GLIBC_VARIABLES = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "GLIBC_TUNABLES")


def retain_freed_memory(mmap_bytes: int = MMAP_THRESHOLD,
                        trim_bytes: int = TRIM_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``mmap_bytes`` and its trim threshold at ``trim_bytes``.

    Returns whether the thresholds were set: False off glibc, or when the environment sets
    glibc's malloc tunables (the process's own choice wins).

    Example::

        >>> from solver.core.allocator import retain_freed_memory
        >>> isinstance(retain_freed_memory(), bool)
        True
    """
    if not sys.platform.startswith("linux") or any(v in os.environ for v in _GLIBC_VARIABLES):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_bytes))
                and mallopt(_M_TRIM_THRESHOLD, int(trim_bytes)))
