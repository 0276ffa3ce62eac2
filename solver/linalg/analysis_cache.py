"""Per-process cache of PARDISO analyses, keyed by sparsity pattern.

The analysis -- fill-reducing ordering (METIS nested dissection, PARDISO's default) and
symbolic factorization, about two thirds of a cold factorization of the reconstruction
system -- depends only on the sparsity pattern. Each process keeps it per pattern (a 128-bit
digest of the upper triangle's CSR index arrays, whether an ordering hint was given and
MKL's thread count, :func:`solver.linalg.pardiso.pattern_key`: an analysis made for one
thread count fails at another), LRU, within :data:`ANALYSIS_CACHE_BYTES`: the
handles of dead factorizations, with their analysis and, memory allowing, their factor's
memory, and for a hinted pattern the ordering. A factorization of a known pattern takes such
a handle and runs only the numerical factorization (PARDISO phase 22), or, if every handle
of the pattern belongs to a live factorization, a new handle: with the kept ordering for a
hinted pattern (the symbolic factorization is redone), else a whole new analysis. Unhinted
patterns keep no ordering because PARDISO returns it only as a user permutation
(``iparm[4] = 2``), and any user permutation turns its two-level factorization into the
classic one, whose solves cost 1.3-1.5x more (``bench/drag_regression.py``). No handle is
ever shared by two live factorizations, so this is thread safe.
"""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .pardiso import PardisoHandle

ANALYSIS_CACHE_BYTES: int = 512 * 2**20
"""Memory limit (bytes) of this process's cache of PARDISO analyses (orderings and symbolic
factorizations, keyed by sparsity pattern, and the factor memory of idle handles, dropped
first; see :func:`analysis_cache_info`). Assign a new value at any time (here or as
``solver.linalg.ANALYSIS_CACHE_BYTES``); it applies from the next factorization. 0 disables
the cache."""


@dataclass
class _CacheEntry:
    """What the cache keeps for one sparsity pattern.

    Attributes:
        perm: the fill-reducing ordering (int32, zero-based) of a pattern factorized with an
            ordering hint; None for PARDISO's own (two-level) ordering, which it does not
            return.
        idle: analysed handles without an owner.
    """

    perm: np.ndarray | None
    idle: list[PardisoHandle] = field(default_factory=list)

    @property
    def nbytes(self) -> int:
        """Bytes of the ordering and of every idle handle."""
        own = 0 if self.perm is None else self.perm.nbytes
        return own + sum(h.held_bytes for h in self.idle)


class AnalysisCache:
    """Per-process LRU cache of PARDISO analyses, keyed by sparsity pattern.

    For each pattern it keeps the fill-reducing ordering (``4 N`` bytes) and the handles of
    factorizations that were garbage collected, with their analysis (ordering + symbolic
    factorization) and, while memory allows, the memory of their numerical factor. A new
    factorization of the same pattern takes an idle handle for itself (then it pays only the
    numerical factorization, phase 22, in memory that is already mapped: on this project's
    VM, faulting a fresh factor's pages in cost 10-30 % of a warm factorization) or, when
    all handles of that pattern are in use, a fresh handle with the kept ordering (phase 11
    skips the ordering but redoes the symbolic factorization). A handle is never shared by
    two live factorizations, so factorizations of one pattern run in parallel safely. The
    total size stays below :data:`ANALYSIS_CACHE_BYTES`: least recently used patterns lose
    their idle handles' factors first, then their idle handles, then their ordering.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._entries: OrderedDict[bytes, _CacheEntry] = OrderedDict()
        self._returned: deque[tuple[bytes, PardisoHandle]] = deque()  # from finalizers
        self._counts = {"computed": 0, "cached_handle": 0, "cached_ordering": 0}
        self._bytes = 0

    def acquire(self, key: bytes) -> tuple[PardisoHandle | None, np.ndarray | None]:
        """Take what the cache has for a pattern.

        Args:
            key: the pattern's key (:func:`solver.linalg.pardiso.pattern_key`).

        Returns:
            ``(handle, perm)``: an idle analysed handle (now owned by the caller) and the
            kept ordering; ``(None, perm)`` when no handle is idle; ``(None, None)`` for an
            unknown pattern or one without a kept ordering.
        """
        with self._lock:
            self._drain()
            entry = self._entries.get(key)
            if entry is None:
                self._counts["computed"] += 1
                return None, None
            self._entries.move_to_end(key)
            if entry.idle:
                handle = entry.idle.pop()
                self._bytes -= handle.held_bytes
                self._counts["cached_handle"] += 1
                return handle, entry.perm
            self._counts["computed" if entry.perm is None else "cached_ordering"] += 1
            return None, entry.perm

    def remember(self, key: bytes, perm: np.ndarray | None) -> None:
        """Keep a pattern, so that idle handles of it are kept.

        Args:
            key: the pattern's key.
            perm: (N,) int32 ordering PARDISO returned for it, or None.
        """
        with self._lock:
            self._drain()
            if key not in self._entries:
                entry = _CacheEntry(None if perm is None else perm.copy())
                self._entries[key] = entry
                self._bytes += entry.nbytes
            self._entries.move_to_end(key)
            self._evict()

    def park(self, key: bytes, handle: PardisoHandle) -> None:
        """Take back the handle of a dead factorization.

        Called by its finalizer, in any thread, possibly during garbage collection: so no
        lock here, only an atomic append; the handle, factor memory included, is filed at
        the next cache operation.

        Args:
            key: the handle's pattern key.
            handle: the analysed handle, factor included.
        """
        self._returned.append((key, handle))

    def _drain(self) -> None:
        """File returned handles under their pattern (lock held), then evict."""
        while self._returned:
            key, handle = self._returned.popleft()
            entry = self._entries.get(key)
            if entry is None:
                handle.release()
                continue
            entry.idle.append(handle)
            self._bytes += handle.held_bytes
        self._evict()

    def _drop_factors(self, limit: float) -> None:
        """Free idle handles' factors, least recently used first, until the cache holds at
        most ``limit`` bytes (lock held)."""
        for entry in self._entries.values():
            for handle in entry.idle:
                if self._bytes <= limit:
                    return
                self._bytes -= handle.factor_bytes
                handle.drop_factor()

    def _evict(self) -> None:
        """Free least recently used factors, then analyses, until the cache fits its limit
        (lock held)."""
        self._drop_factors(ANALYSIS_CACHE_BYTES)
        for key in list(self._entries):
            if self._bytes <= ANALYSIS_CACHE_BYTES:
                return
            entry = self._entries[key]
            while entry.idle and self._bytes > ANALYSIS_CACHE_BYTES:
                handle = entry.idle.pop(0)
                self._bytes -= handle.held_bytes
                handle.release()
            if self._bytes > ANALYSIS_CACHE_BYTES:
                self._bytes -= entry.nbytes
                del self._entries[key]

    def clear(self) -> None:
        """Free every kept analysis and reset the counters (live handles are unaffected)."""
        with self._lock:
            self._drain()
            for entry in self._entries.values():
                for handle in entry.idle:
                    handle.release()
            self._entries.clear()
            self._bytes = 0
            self._counts = dict.fromkeys(self._counts, 0)

    def release_factors(self) -> None:
        """Free the factors of every idle handle, keeping their analyses."""
        with self._lock:
            self._drain()
            self._drop_factors(0)

    def info(self) -> dict[str, int]:
        """Sizes and counters (see :func:`analysis_cache_info`)."""
        with self._lock:
            self._drain()
            idle = [h for e in self._entries.values() for h in e.idle]
            return {"patterns": len(self._entries), "idle_handles": len(idle),
                    "bytes": self._bytes, "factor_bytes": sum(h.factor_bytes for h in idle),
                    "limit_bytes": int(ANALYSIS_CACHE_BYTES), **self._counts}


CACHE = AnalysisCache()
"""This process's analysis cache."""


def clear_analysis_cache() -> None:
    """Free every analysis kept by this process and reset the counters.

    Live factorizations keep working; the counters are those of :func:`analysis_cache_info`.
    """
    CACHE.clear()


def release_cached_factors() -> None:
    """Free the numerical factors kept by idle PARDISO handles of this process's cache.

    Their analyses stay (the next factorization of a pattern pays its page faults again,
    not its analysis). For a process about to sit idle.
    """
    CACHE.release_factors()


def analysis_cache_info() -> dict[str, int]:
    """The analysis cache of this process.

    Returns:
        ``patterns`` (sparsity patterns kept), ``idle_handles`` (analysed PARDISO handles
        without an owner), ``bytes`` (their size and the orderings'), ``factor_bytes`` (the
        part of it that is idle handles' numerical factors, see
        :func:`release_cached_factors`), ``limit_bytes`` (:data:`ANALYSIS_CACHE_BYTES`), and
        how many PARDISO factorizations ``computed`` their analysis, reused an idle handle
        (``cached_handle``: numerical factorization only) or reused an ordering
        (``cached_ordering``: symbolic factorization and numerical factorization).

    Example:
        >>> from solver.linalg import analysis_cache_info, clear_analysis_cache
        >>> clear_analysis_cache()
        >>> info = analysis_cache_info()
        >>> info["patterns"], info["computed"], info["bytes"]
        (0, 0, 0)
    """
    return CACHE.info()
