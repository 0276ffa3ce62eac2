"""Sparse symmetric-positive-definite factorization with selectable backends.

Factorize a sparse SPD matrix ``K`` once, then solve ``K x = b`` for as many right-hand
sides as needed; each solve only back-substitutes::

    fact = factorize(K)               # backend="auto": the fastest one installed
    x = fact.solve(b)                 # b: (N,) or (N, k) float64 -> same shape

Backends, fastest first on the reference machine (2-core x86_64; factorization plus one
solve of 3 right-hand sides, numbers in ``bench/LINALG.md``):

``"pardiso"``
    Intel oneMKL PARDISO, real SPD mode (``mtype=2``), upper triangle in zero-based CSR,
    called directly through ``ctypes`` so that the factor stays inside MKL between
    solves and nothing is copied per solve. Needs the MKL runtime ``libmkl_rt``, which
    ``pip install pypardiso`` brings (it depends on the ``mkl`` wheel); x86_64 only.
    2-10x faster than the others from 70K unknowns on, and the smallest factor. It
    releases the GIL and uses MKL's OpenMP threads, by default one per core. Limit them
    with ``MKL_NUM_THREADS`` (and ``OMP_NUM_THREADS``) set before the process loads MKL
    when several processes factorize at once: ``threadpoolctl`` does not see the MKL
    library loaded here through ``ctypes``, so its limits do not reach PARDISO (the
    service's worker processes set the environment variables at start-up).
``"superlu"``
    SciPy's SuperLU (``scipy.sparse.linalg.splu``) with the minimum-degree ordering on
    ``K + K^T`` and diagonal pivoting (``SymmetricMode``, ``diag_pivot_thresh=0``).
    Always available; single-threaded; releases the GIL. It is an LU factorization, so
    it needs about twice the memory of a Cholesky factor, and it does *not* reject a
    matrix that is symmetric indefinite but nonsingular: it solves it correctly instead
    of raising.
``"cholespy"``
    CHOLMOD (SuiteSparse) Cholesky ``L L^T`` through ``pip install cholespy``, from the
    lower triangle. Its factorization is as fast as SuperLU's or up to 1.4x slower (the
    wheel bundles the unoptimized reference BLAS), so ``"auto"`` never picks it while
    SuperLU works; choose it explicitly for less memory than SuperLU (up to half) and
    1.5-3x faster solves (many solves per factorization). Single-threaded; holds the GIL
    while it factorizes. CHOLMOD prints a one-line "not positive definite" warning to
    stdout when it rejects a matrix.

Not backends: ``python-mumps`` 0.0.2 does not import with NumPy 2; ``sksparse-minimal``
0.3 provides no ``sksparse`` module (only ``sksparse_minimal``).

Errors: an unknown backend name raises :class:`ValueError`; a known but uninstalled one
raises :class:`BackendUnavailableError` (a ``ValueError`` and an ``ImportError``) naming
the pip package. A matrix that is singular or not positive definite raises
:class:`SingularSystemError`, either from the factorization or from :meth:`solve`,
which checks the relative residual ``||K x - b|| / ||b||`` of every column it returns
(one sparse matrix product) and refuses results above :data:`RESIDUAL_TOLERANCE`.

Pickling: every :class:`Factorization` pickles, whatever the backend, but no native
factor is ever serialized (none of the three libraries can export one). The pickle
holds the backend name and the matrix (CSR arrays, about ``12 * nnz(K)`` bytes), and
unpickling **factorizes again** in the receiving process, which costs one factorization
there and raises :class:`BackendUnavailableError` if that process lacks the backend.
For worker pools it is therefore as cheap to send the matrix and call :func:`factorize`
in the worker.

Analysis cache (PARDISO): the analysis -- fill-reducing ordering (METIS nested dissection,
PARDISO's default) and symbolic factorization, about two thirds of a cold factorization of
the reconstruction system -- depends only on the sparsity pattern. Each process keeps it
per pattern (a 128-bit digest of the upper triangle's CSR index arrays and whether an
ordering hint was given), LRU, within :data:`ANALYSIS_CACHE_BYTES`: the handles of dead
factorizations, with their analysis and, memory allowing, their factor's memory, and for a
hinted pattern the ordering. A factorization of a known pattern takes such a handle and
runs only the numerical factorization (PARDISO phase 22), or, if every handle of the
pattern belongs to a live factorization, a new handle: with the kept ordering for a hinted
pattern (the symbolic factorization is redone), else a whole new analysis. Unhinted
patterns keep no ordering because PARDISO returns it only as a user permutation
(``iparm[4] = 2``), and any user permutation turns its two-level factorization into the
classic one, whose solves cost 1.3-1.5x more (``bench/drag_regression.py``). No handle is
ever shared by two live factorizations, so this is thread safe. ``Factorization.analysis``
says ``"cached"`` or ``"computed"``;
:func:`analysis_cache_info` and :func:`clear_analysis_cache` inspect and empty the cache.
Repeated factorizations of one pattern with new values (refinement iterations, successive
reconstructs of one mesh, new handle sets) therefore skip the analysis without any change
to the calls. SuperLU and cholespy always compute their analysis.

Thread safety: :meth:`Factorization.solve` may be called from several threads; solves on
one factorization are serialized by a lock (the native solvers reuse workspaces), and
different factorizations run in parallel where the backend releases the GIL.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import hashlib
import os
import sys
import threading
import time
import weakref
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp

__all__ = [
    "ANALYSIS_CACHE_BYTES",
    "BACKENDS",
    "RESIDUAL_TOLERANCE",
    "BackendUnavailableError",
    "Factorization",
    "SingularSystemError",
    "analysis_cache_info",
    "available_backends",
    "clear_analysis_cache",
    "default_backend",
    "factorize",
    "resolve_backend",
]

BACKENDS: tuple[str, ...] = ("pardiso", "superlu", "cholespy")
"""Every backend name :func:`factorize` knows, fastest first (see ``bench/LINALG.md``)."""

RESIDUAL_TOLERANCE: float = 1e-6
REFINEMENT_STEPS: int = 3  # iterative-refinement steps tried before a solve is refused
"""Largest accepted relative residual ``||K x - b|| / ||b||`` of a solved column."""

ANALYSIS_CACHE_BYTES: int = 512 * 2**20
"""Memory limit (bytes) of this process's cache of PARDISO analyses (orderings and symbolic
factorizations, keyed by sparsity pattern, and the factor memory of idle handles, dropped
first; see :func:`analysis_cache_info`). Assign a new value at any time; it applies from the
next factorization. 0 disables the cache."""

_PIP_PACKAGE: dict[str, str] = {"pardiso": "pypardiso", "cholespy": "cholespy", "superlu": "scipy"}

_INT32_MAX = np.iinfo(np.int32).max


class BackendUnavailableError(ValueError, ImportError):
    """A known backend whose library cannot be loaded in this environment.

    It is both a :class:`ValueError` (a bad ``backend`` argument) and an
    :class:`ImportError` (a missing optional dependency); the message names the pip
    package to install.
    """


class SingularSystemError(RuntimeError):
    """The matrix is singular or not positive definite (the factorization failed, or a
    solve produced a non-finite or inaccurate result)."""


# --------------------------------------------------------------------------- backends


class _NativeSolver(Protocol):
    """What each backend provides: a factor of the matrix and a solve with it."""

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve for ``rhs`` of shape (N, k) float64; return (N, k) float64."""
        ...


# -- MKL PARDISO ---------------------------------------------------------------------

_PARDISO_ERRORS: dict[int, str] = {
    -1: "input inconsistent",
    -2: "not enough memory",
    -3: "reordering problem",
    -4: "zero or negative pivot: the matrix is not positive definite",
    -5: "unclassified (internal) error",
    -6: "reordering failed",
    -7: "diagonal matrix is singular",
    -8: "32-bit integer overflow",
    -9: "not enough memory for out-of-core mode",
    -10: "error opening out-of-core files",
    -11: "read/write error with out-of-core files",
    -12: "pardiso_64 called from a 32-bit library",
    -13: "interrupted by the mkl_progress callback",
    -15: "internal error during the iparm[35] (Schur complement) setup",
}

_PARDISO_MTYPE_SPD = 2

# Zero-based entries of MKL's iparm applied on top of pardisoinit()'s defaults for
# mtype=2 (which already select the parallel nested-dissection ordering, iparm[1]=3).
_PARDISO_IPARM: dict[int, int] = {
    7: 0,  # no iterative refinement: solves are 2-4x cheaper; the residual check guards
    18: 0,  # do not count flops (pardisoinit asks for it; costs analysis time)
    23: 1,  # two-level factorization: faster solves and no slower factorization here
    34: 1,  # zero-based ia/ja, so scipy's CSR arrays are passed as they are
}


class _Mkl:
    """The ``libmkl_rt`` entry points PARDISO needs, loaded once per process."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        i32p = ctypes.POINTER(ctypes.c_int32)
        vp = ctypes.c_void_p
        self.lib = lib
        set_layer = lib.MKL_Set_Interface_Layer
        set_layer.argtypes = [ctypes.c_int]
        set_layer.restype = ctypes.c_int
        layer = set_layer(0)  # MKL_INTERFACE_LP64: 32-bit integers
        if layer < 0 or layer & 1:
            raise ImportError(f"libmkl_rt uses the ILP64 interface (layer {layer}); "
                              "unset MKL_INTERFACE_LAYER to use PARDISO")
        self.pardiso = lib.pardiso
        self.pardiso.argtypes = [vp, i32p, i32p, i32p, i32p, i32p, vp, vp, vp, vp, i32p, vp,
                                 i32p, vp, vp, i32p]
        self.pardiso.restype = None
        self.pardisoinit = lib.pardisoinit
        self.pardisoinit.argtypes = [vp, i32p, vp]
        self.pardisoinit.restype = None


@functools.cache
def _mkl() -> _Mkl:
    """Load ``libmkl_rt`` (raises ``ImportError`` when it cannot be found or loaded).

    Looks where pip's ``mkl`` wheel puts it (``<sys.prefix>/lib``) or at
    ``$PYPARDISO_MKL_RT``; only if that fails, imports :mod:`pypardiso` and uses the
    library its (slower, recursive) search found.
    """
    candidates = [os.environ.get("PYPARDISO_MKL_RT", "")]
    for prefix in dict.fromkeys((sys.prefix, sys.base_prefix)):
        candidates += sorted(glob.glob(os.path.join(prefix, "lib", "libmkl_rt.so*")), key=len)
    for path in filter(None, candidates):
        try:
            return _Mkl(ctypes.CDLL(path))
        except (OSError, AttributeError):
            continue
    try:
        import pypardiso  # optional: imported lazily
    except (ImportError, OSError) as exc:
        raise ImportError(f"libmkl_rt not found: {exc}") from exc
    return _Mkl(pypardiso.ps.libmkl)


class _PardisoHandle:
    """One PARDISO handle (``pt``, ``iparm`` and the ordering ``perm``) and the MKL memory
    it holds. Exactly one owner uses a handle at a time (a live solver, or the analysis
    cache while it is idle), so no lock is needed around its calls.

    ``perm`` given: PARDISO uses that ordering (``iparm[4] = 1``). Else it orders the matrix
    itself, and returns its ordering in ``perm`` only if ``return_ordering``
    (``iparm[4] = 2``). Either user-permutation mode silently turns the two-level
    factorization (``iparm[23] = 1``) into the classic one, whose solves cost 1.3-1.5x more
    (bench/drag_regression.py): only a handle with neither keeps the two-level factor.
    """

    def __init__(self, mkl: _Mkl, n: int, perm: np.ndarray | None,
                 return_ordering: bool = False) -> None:
        self.mkl = mkl
        self.n = n
        self.pt = np.zeros(64, dtype=np.int64)  # opaque handle: must never be touched
        self.iparm = np.zeros(64, dtype=np.int32)
        mtype = ctypes.c_int32(_PARDISO_MTYPE_SPD)
        mkl.pardisoinit(self.pt.ctypes.data, ctypes.byref(mtype), self.iparm.ctypes.data)
        for index, value in _PARDISO_IPARM.items():
            self.iparm[index] = value
        # iparm[4] = 0: PARDISO's own ordering, not returned; 1: use the ordering in perm;
        # 2: compute it and return it in perm.
        self.perm: np.ndarray | None = None
        if perm is not None:
            self.perm, self.iparm[4] = perm.copy(), 1
        elif return_ordering:
            self.perm, self.iparm[4] = np.zeros(n, dtype=np.int32), 2
        self.factored = False  # holds a numerical factor (phase 22 done, no phase 0 since)

    def call(self, phase: int, a: np.ndarray, ia: np.ndarray, ja: np.ndarray,
             b: np.ndarray | None = None, x: np.ndarray | None = None, nrhs: int = 1) -> int:
        """Run PARDISO ``phase`` on the upper-triangle CSR ``(a, ia, ja)``; its error code."""
        one = ctypes.c_int32(1)
        err = ctypes.c_int32(0)
        self.mkl.pardiso(
            self.pt.ctypes.data, ctypes.byref(one), ctypes.byref(one),
            ctypes.byref(ctypes.c_int32(_PARDISO_MTYPE_SPD)), ctypes.byref(ctypes.c_int32(phase)),
            ctypes.byref(ctypes.c_int32(self.n)), a.ctypes.data, ia.ctypes.data, ja.ctypes.data,
            None if self.perm is None else self.perm.ctypes.data,
            ctypes.byref(ctypes.c_int32(nrhs)), self.iparm.ctypes.data,
            ctypes.byref(ctypes.c_int32(0)), None if b is None else b.ctypes.data,
            None if x is None else x.ctypes.data, ctypes.byref(err))
        return err.value

    def _call_without_matrix(self, phase: int) -> None:
        idx = np.zeros(2, dtype=np.int32)
        self.call(phase, np.zeros(1), idx, idx)

    def drop_factor(self) -> None:
        """Free the numerical factor, keep the analysis (phase 0)."""
        self._call_without_matrix(0)
        self.factored = False

    def release(self) -> None:
        """Free all MKL memory of the handle (phase -1)."""
        self._call_without_matrix(-1)

    @property
    def analysis_bytes(self) -> int:
        """Memory the analysis keeps after :meth:`drop_factor` (iparm[15], in KB), plus perm."""
        return int(self.iparm[15]) * 1024 + (0 if self.perm is None else self.perm.nbytes)

    @property
    def factor_bytes(self) -> int:
        """Memory of the numerical factor while it is held (iparm[16], in KB), else 0."""
        return int(self.iparm[16]) * 1024 if self.factored else 0

    @property
    def held_bytes(self) -> int:
        """All the memory the handle holds: analysis, ordering and factor."""
        return self.analysis_bytes + self.factor_bytes


# --------------------------------------------------------------------- analysis cache


@dataclass
class _CacheEntry:
    """What the cache keeps for one sparsity pattern."""

    # The fill-reducing ordering (int32, zero-based) of a pattern factorized with an ordering
    # hint; None for PARDISO's own (two-level) ordering, which it does not return.
    perm: np.ndarray | None
    idle: list[_PardisoHandle] = field(default_factory=list)  # analysed, no owner

    @property
    def nbytes(self) -> int:
        own = 0 if self.perm is None else self.perm.nbytes
        return own + sum(h.held_bytes for h in self.idle)


class _AnalysisCache:
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
        self._returned: deque[tuple[bytes, _PardisoHandle]] = deque()  # from finalizers
        self._counts = {"computed": 0, "cached_handle": 0, "cached_ordering": 0}
        self._bytes = 0

    def acquire(self, key: bytes) -> tuple[_PardisoHandle | None, np.ndarray | None]:
        """An idle analysed handle of pattern ``key`` (now owned by the caller), else the
        kept ordering, else ``(None, None)``."""
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
        """Keep pattern ``key`` (and its ordering, if PARDISO returned one), so that idle
        handles of it are kept."""
        with self._lock:
            self._drain()
            if key not in self._entries:
                entry = _CacheEntry(None if perm is None else perm.copy())
                self._entries[key] = entry
                self._bytes += entry.nbytes
            self._entries.move_to_end(key)
            self._evict()

    def park(self, key: bytes, handle: _PardisoHandle) -> None:
        """Take back the handle of a dead factorization (called by its finalizer, in any
        thread, possibly during garbage collection: so no lock here, only an atomic
        append; the handle, factor memory included, is filed at the next cache operation)."""
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
        """Free every kept analysis and reset the counters; handles of live
        factorizations are not affected."""
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


_CACHE = _AnalysisCache()


def clear_analysis_cache() -> None:
    """Free every analysis kept by this process and reset the counters of
    :func:`analysis_cache_info` (live factorizations keep working)."""
    _CACHE.clear()


def release_cached_factors() -> None:
    """Free the numerical factors kept by idle PARDISO handles of this process's analysis
    cache; their analyses stay (the next factorization of a pattern pays its page faults
    again, not its analysis). For a process about to sit idle."""
    _CACHE.release_factors()


def analysis_cache_info() -> dict[str, int]:
    """The analysis cache of this process: ``patterns`` (sparsity patterns kept),
    ``idle_handles`` (analysed PARDISO handles without an owner), ``bytes`` (their size
    and the orderings'), ``factor_bytes`` (the part of it that is idle handles' numerical
    factors, see :func:`release_cached_factors`), ``limit_bytes``
    (:data:`ANALYSIS_CACHE_BYTES`), and how many PARDISO factorizations ``computed`` their
    analysis, reused an idle handle (``cached_handle``: numerical factorization only) or
    reused an ordering (``cached_ordering``: symbolic factorization and numerical
    factorization)."""
    return _CACHE.info()


def _pattern_key(n: int, ia: np.ndarray, ja: np.ndarray, hinted: bool) -> bytes:
    """128-bit digest of an upper-triangle CSR pattern and the PARDISO settings; ``hinted``:
    ordered from a ``groups`` hint (classic factor) rather than by PARDISO (two-level)."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(repr((n, len(ja), hinted, sorted(_PARDISO_IPARM.items()))).encode())
    digest.update(memoryview(ia))
    digest.update(memoryview(ja))
    return digest.digest()


def _retire(handle: _PardisoHandle, key: bytes) -> None:
    """Finalizer of a PARDISO solver: give its analysis to the cache, or free it."""
    if ANALYSIS_CACHE_BYTES > 0:
        _CACHE.park(key, handle)
    else:
        handle.release()


def _compressed_pattern(ia: np.ndarray, ja: np.ndarray, groups: np.ndarray,
                        n_groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upper-triangle CSR ``(a, ia, ja)`` of the graph with one node per group: nodes ``g``
    and ``h`` are joined where some unknown of ``g`` couples with one of ``h`` in the
    upper-triangle pattern ``(ia, ja)`` of an (N, N) matrix; ``groups`` (N,) int. The values
    make it diagonally dominant; they must be nonzero, since PARDISO's ordering skips
    explicitly stored zeros (measured: zero values gave nearly no fill reduction)."""
    rows = np.repeat(groups, np.diff(ia))
    cols = groups[ja]
    lo, hi = np.minimum(rows, cols), np.maximum(rows, cols)
    off = lo != hi
    graph = sp.csr_array((np.ones(int(off.sum())), (lo[off], hi[off])),
                         shape=(n_groups, n_groups))
    graph.sum_duplicates()
    graph.data[:] = -1.0
    degree = np.bincount(np.repeat(np.arange(n_groups), np.diff(graph.indptr)),
                         minlength=n_groups) + np.bincount(graph.indices, minlength=n_groups)
    graph = sp.csr_array(graph + sp.diags_array(degree + 1.0, format="csr"))
    graph.sum_duplicates()
    return (np.ascontiguousarray(graph.data, dtype=np.float64),
            graph.indptr.astype(np.int32), graph.indices.astype(np.int32))


def _group_ordering(mkl: _Mkl, ia: np.ndarray, ja: np.ndarray,
                    groups: np.ndarray) -> np.ndarray:
    """Fill-reducing ordering (N,) int32 of the unknowns from PARDISO's ordering of the
    compressed graph (one node per group, :func:`_compressed_pattern`): the unknowns of
    each group stay together, in the order of their group (PARDISO's ``perm`` lists old
    indices by new position). The compressed graph has a fraction of the nodes and edges,
    so its nested dissection costs a fraction of the full one's."""
    n_groups = int(groups.max()) + 1
    a, cia, cja = _compressed_pattern(ia, ja, groups, n_groups)
    handle = _PardisoHandle(mkl, n_groups, None, return_ordering=True)
    try:
        error = handle.call(11, a, cia, cja)
        if error:
            raise RuntimeError(f"PARDISO ordering of the compressed graph failed: error "
                               f"{error} ({_PARDISO_ERRORS.get(error, '?')})")
        position = np.empty(n_groups, dtype=np.int64)
        position[handle.perm] = np.arange(n_groups)
    finally:
        handle.release()
    return np.argsort(position[groups], kind="stable").astype(np.int32)


class _PardisoSolver:
    """MKL PARDISO factor of an SPD matrix, from its upper triangle.

    Attributes ``analysis`` ("cached" or "computed") and ``timings`` (seconds of
    ``"analysis"`` -- ordering and symbolic factorization -- and ``"factorization"``).
    ``groups`` (N,) int, optional: unknowns that always couple alike (e.g. the three
    unknowns of one face frame); a computed ordering then orders the compressed graph
    (:func:`_group_ordering`) instead of the whole matrix.
    """

    def __init__(self, matrix: sp.csr_array, groups: np.ndarray | None = None,
                 upper: bool = False) -> None:
        mkl = _mkl()
        upper = matrix if upper else _upper_triangle(matrix)
        self.n = int(upper.shape[0])
        # PARDISO reads these arrays in every phase: keep them alive and unchanged.
        self._ia = np.ascontiguousarray(upper.indptr, dtype=np.int32)
        self._ja = np.ascontiguousarray(upper.indices, dtype=np.int32)
        self._a = np.ascontiguousarray(upper.data, dtype=np.float64)
        key = _pattern_key(self.n, self._ia, self._ja, groups is not None)
        handle, perm = _CACHE.acquire(key) if ANALYSIS_CACHE_BYTES > 0 else (None, None)
        reused = handle is not None
        self.analysis = "cached" if reused or perm is not None else "computed"
        start = time.perf_counter()
        if handle is None:
            if perm is None and groups is not None:
                perm = _group_ordering(mkl, self._ia, self._ja, groups)
            handle = _PardisoHandle(mkl, self.n, perm)
            error = handle.call(11, self._a, self._ia, self._ja)  # ordering + symbolic
            self._raise_if_failed(handle, error)
            if self.analysis == "computed" and ANALYSIS_CACHE_BYTES > 0:
                _CACHE.remember(key, handle.perm)
        analysed = time.perf_counter()
        self._handle = handle
        self._raise_if_failed(handle, handle.call(22, self._a, self._ia, self._ja))
        handle.factored = True
        self.timings = {"analysis": 0.0 if reused else analysed - start,
                        "factorization": time.perf_counter() - analysed}
        self._finalizer = weakref.finalize(self, _retire, handle, key)

    @staticmethod
    def _raise_if_failed(handle: _PardisoHandle, error: int) -> None:
        """Free ``handle`` and raise if PARDISO reported ``error`` != 0."""
        if not error:
            return
        handle.release()
        message = (f"PARDISO factorization failed: error {error} "
                   f"({_PARDISO_ERRORS.get(error, '?')})")
        if error in (-4, -7):
            raise SingularSystemError(message)
        if error == -2:
            raise MemoryError(message)
        raise RuntimeError(message)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Forward/back substitution; ``rhs`` (N, k) float64 -> (N, k) float64."""
        b = np.asfortranarray(rhs, dtype=np.float64)  # PARDISO wants column-major columns
        x = np.zeros_like(b, order="F")
        error = self._handle.call(33, self._a, self._ia, self._ja, b, x, b.shape[1])
        if error:
            raise RuntimeError(f"PARDISO solve failed: error {error} "
                               f"({_PARDISO_ERRORS.get(error, '?')})")
        return x


# -- cholespy (CHOLMOD) ---------------------------------------------------------------


class _CholespySolver:
    """CHOLMOD ``L L^T`` factor via cholespy, from the lower triangle."""

    def __init__(self, matrix: sp.csr_array) -> None:
        import cholespy  # optional: imported lazily

        # Pass CSR: cholespy copies CSR/COO input, whereas it sorts CSC input in place and
        # reallocates it (unsafe on NumPy-owned memory). CHOLMOD reads the lower triangle.
        lower = sp.tril(matrix, format="csr")
        try:
            self._solver = cholespy.CholeskySolverD(
                int(matrix.shape[0]), lower.indptr.astype(np.int32, copy=False),
                lower.indices.astype(np.int32, copy=False),
                np.ascontiguousarray(lower.data, dtype=np.float64), cholespy.MatrixType.CSR)
        except ValueError as exc:
            if "positive definite" in str(exc):
                raise SingularSystemError(f"CHOLMOD factorization failed: {exc}") from exc
            raise

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Forward/back substitution; ``rhs`` (N, k) float64 -> (N, k) float64."""
        b = np.ascontiguousarray(rhs, dtype=np.float64)
        x = np.zeros_like(b)
        self._solver.solve(b, x)
        return x


# -- SciPy SuperLU --------------------------------------------------------------------

_SUPERLU_OPTIONS: dict[str, Any] = {
    "permc_spec": "MMD_AT_PLUS_A",  # minimum degree on K + K^T: a symmetric ordering
    "diag_pivot_thresh": 0.0,  # always pivot on the diagonal (stable for SPD)
    "options": {"SymmetricMode": True},
}


class _SuperluSolver:
    """SciPy SuperLU factor of the full (symmetric) matrix."""

    def __init__(self, matrix: sp.csr_array) -> None:
        from scipy.sparse.linalg import splu  # lazy: keeps module import light

        # The CSR arrays of a symmetric matrix are also its CSC arrays: no copy.
        csc = sp.csc_array((matrix.data, matrix.indices, matrix.indptr), shape=matrix.shape)
        try:
            self._lu = splu(csc, **_SUPERLU_OPTIONS)
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise SingularSystemError(f"SuperLU factorization failed: {exc}") from exc

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Forward/back substitution; ``rhs`` (N, k) float64 -> (N, k) float64."""
        return np.asarray(self._lu.solve(np.asfortranarray(rhs, dtype=np.float64)))


class _EmptySolver:
    """The 0 x 0 matrix (no native library accepts it)."""

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Return a copy of the (0, k) ``rhs``."""
        return np.array(rhs, dtype=np.float64)


_SOLVERS: dict[str, Callable[[sp.csr_array], _NativeSolver]] = {
    "pardiso": _PardisoSolver,
    "cholespy": _CholespySolver,
    "superlu": _SuperluSolver,
}


# ------------------------------------------------------------------ backend selection


@functools.cache
def _unavailable_reason(backend: str) -> str | None:
    """``None`` if ``backend`` loads and solves a 2 x 2 system here, else why not."""
    if backend == "superlu":
        return None
    try:
        solver = _SOLVERS[backend](_canonical_matrix(sp.csr_array([[4.0, 1.0], [1.0, 3.0]])))
        x = solver.solve(np.array([[5.0], [4.0]]))
    except ImportError as exc:
        return f"{type(exc).__name__}: {exc}"
    except Exception as exc:  # any failure means "do not use it"
        return f"smoke test failed: {type(exc).__name__}: {exc}"
    if not np.allclose(x.ravel(), [1.0, 1.0], rtol=1e-12, atol=0.0):
        return f"smoke test returned a wrong solution {x.ravel().tolist()}"
    return None


def available_backends() -> list[str]:
    """Backends usable in this process, fastest first; always includes ``"superlu"``.

    The first call loads each optional library and solves a 2 x 2 system with it
    (about 30 ms in all); the results are cached for the life of the process.
    """
    return [name for name in BACKENDS if _unavailable_reason(name) is None]


def default_backend() -> str:
    """The fastest available backend (what ``backend="auto"`` selects)."""
    return available_backends()[0]


def resolve_backend(backend: str) -> str:
    """Map ``"auto"`` to the default backend and validate a backend name.

    Returns an available backend name; raises ``ValueError`` for an unknown name and
    :class:`BackendUnavailableError` for a known one that cannot be loaded here. Call it
    before any work on paths that may not factorize at all (e.g. tree integration), so an
    invalid choice is refused on every path.
    """
    if backend == "auto":
        return default_backend()
    if backend not in BACKENDS:
        valid = ", ".join(repr(name) for name in ("auto", *BACKENDS))
        raise ValueError(f"unknown linear-algebra backend {backend!r}; valid names: {valid}")
    reason = _unavailable_reason(backend)
    if reason is not None:
        raise BackendUnavailableError(
            f"backend {backend!r} is not available here ({reason}); install it with "
            f"`pip install {_PIP_PACKAGE[backend]}` or use one of {available_backends()}")
    return backend


# ---------------------------------------------------------------------- factorization


def _is_real(dtype: np.dtype) -> bool:
    """Whether ``dtype`` is a real number type (bool, integer or floating point)."""
    return bool(np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)
                or np.issubdtype(dtype, np.bool_))


def _canonical_matrix(matrix: Any, assume_symmetric: bool = False) -> sp.csr_array:
    """Validate ``matrix`` and return an owned, canonical float64 CSR copy (int32 indices).

    Raises ``TypeError`` for a non-sparse or complex matrix and ``ValueError`` for a
    non-square, too large, non-finite or non-symmetric one.
    """
    if not sp.issparse(matrix):
        raise TypeError("matrix must be a scipy.sparse matrix or array, "
                        f"not {type(matrix).__name__}")
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise ValueError(f"matrix must be square, got shape {matrix.shape}")
    if not _is_real(matrix.dtype):
        raise TypeError(f"matrix must be real, got dtype {matrix.dtype}")
    K = sp.csr_array(matrix, dtype=np.float64, copy=True)
    K.sum_duplicates()  # also sorts the column indices of every row
    if max(K.shape[0], K.nnz) > _INT32_MAX:
        raise ValueError("matrix too large for 32-bit sparse indices: "
                         f"shape {K.shape}, nnz {K.nnz}")
    K.indptr = K.indptr.astype(np.int32, copy=False)
    K.indices = K.indices.astype(np.int32, copy=False)
    if not np.isfinite(K.data).all():
        raise SingularSystemError("matrix has non-finite (NaN or infinite) entries: the "
                                  "input values overflow double precision")
    if K.nnz and not assume_symmetric:
        scale = float(np.abs(K.data).max())
        asymmetry = float(abs(K - K.T).max())
        if asymmetry > 1e-10 * scale:
            raise ValueError(f"matrix is not symmetric: max |K - K^T| = {asymmetry:.3g} "
                             f"(max |K| = {scale:.3g})")
    return K


def _upper_triangle(K: sp.csr_array) -> sp.csr_array:
    """Upper triangle of ``K`` (CSR, sorted int32 indices) with every diagonal entry
    stored, explicitly zero if need be (PARDISO requires them)."""
    n = K.shape[0]
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(K.indptr))
    keep = K.indices >= rows
    if np.count_nonzero(K.indices == rows) == n:  # every diagonal stored: mask in place
        indptr = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(np.bincount(rows[keep], minlength=n), out=indptr[1:])
        return sp.csr_array((K.data[keep], K.indices[keep], indptr), shape=K.shape)
    strict = sp.triu(K, k=1, format="coo")
    diagonal = np.arange(n, dtype=np.int64)
    upper = sp.csr_array(
        (np.concatenate([strict.data, K.diagonal()]),
         (np.concatenate([strict.row, diagonal]), np.concatenate([strict.col, diagonal]))),
        shape=K.shape)
    upper.sum_duplicates()
    upper.indptr = upper.indptr.astype(np.int32, copy=False)
    upper.indices = upper.indices.astype(np.int32, copy=False)
    return upper


class Factorization:
    """A factorized sparse SPD matrix ``K``; :meth:`solve` only back-substitutes.

    Create it with :func:`factorize`. Attributes: ``backend`` (the backend name that
    computed it), ``size`` (N, the order of ``K``), ``analysis`` (``"cached"`` when the
    fill-reducing ordering of a factorization with the same sparsity pattern was reused
    from this process's analysis cache -- PARDISO only --, else ``"computed"``) and
    ``timings`` (seconds: ``"analysis"``, the ordering and symbolic factorization, 0 when
    a cached handle was reused; ``"factorization"``, the numerical factorization; other
    backends report their whole factorization under ``"factorization"``). It keeps a
    private copy of ``K`` (for the residual check and for pickling) besides the factor.
    """

    backend: str
    size: int
    analysis: str
    timings: dict[str, float]

    def __init__(self, matrix: sp.csr_array, backend: str,
                 groups: np.ndarray | None = None, upper: bool = False) -> None:
        """Factorize ``matrix`` (canonical float64 CSR, symmetric; with ``upper`` only its
        upper triangle, every diagonal entry stored) with ``backend`` (a validated,
        available name) and the ordering hint ``groups`` (validated (N,) int64 or None).
        Use :func:`factorize` rather than this."""
        self.backend = backend
        self.size = int(matrix.shape[0])
        self._upper = upper and backend == "pardiso"  # PARDISO reads the triangle as is
        if upper and not self._upper:
            matrix = _symmetric_from_upper(matrix)
        self._matrix = matrix
        self._groups = groups
        self._lock = threading.Lock()
        self._verified = False  # set by the first solve whose residual is checked
        start = time.perf_counter()
        if self.size == 0:
            self._solver: _NativeSolver = _EmptySolver()
        else:
            self._solver = (_PardisoSolver(matrix, groups, self._upper)
                            if backend == "pardiso" else _SOLVERS[backend](matrix))
        self.analysis = getattr(self._solver, "analysis", "computed")
        self.timings = getattr(self._solver, "timings",
                               {"analysis": 0.0, "factorization": time.perf_counter() - start})

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve ``K x = rhs``.

        ``rhs``: real array of shape (N,) or (N, k) (converted to float64). Returns ``x``
        with the same shape, float64. Raises :class:`SingularSystemError` if some column
        of ``x`` is non-finite or has a relative residual ``||K x - b|| / ||b||`` above
        :data:`RESIDUAL_TOLERANCE` (for ``b = 0``: any nonzero residual), ``ValueError``
        for a wrong shape or non-finite ``rhs``. The residual is checked (and improved by
        iterative refinement if needed) until one solve has passed; after that the factor
        is trusted and only finiteness is checked, so repeated solves cost one
        back-substitution each.
        """
        b = np.asarray(rhs)
        if b.ndim not in (1, 2) or b.shape[0] != self.size:
            raise ValueError(
                f"rhs must have shape ({self.size},) or ({self.size}, k), got {b.shape}")
        if not _is_real(b.dtype):
            raise TypeError(f"rhs must be real, got dtype {b.dtype}")
        b2 = b.astype(np.float64, copy=False)
        if b2.ndim == 1:
            b2 = b2[:, None]
        if not np.isfinite(b2).all():
            raise ValueError("rhs has non-finite (NaN or infinite) entries")
        if b2.shape[1] == 0:
            return np.zeros(b.shape, dtype=np.float64)
        with self._lock:
            x = self._solver.solve(b2)
            if self._verified and np.isfinite(x).all():
                # The factor passed the residual check once: a backward-stable solve with
                # the same factor needs no second opinion (this keeps drags cheap).
                return np.ascontiguousarray(x.reshape(b.shape))
            residual = self._relative_residual(x, b2)
            # Iterative refinement, only when the first answer is not accurate enough
            # (ill-conditioned but nonsingular systems): x += K^-1 (b - K x).
            for _ in range(REFINEMENT_STEPS):
                if residual <= RESIDUAL_TOLERANCE:
                    break
                x = x + self._solver.solve(b2 - self._product(x))
                residual = self._relative_residual(x, b2)
        self._raise_if_inaccurate(x, residual)
        self._verified = True
        return np.ascontiguousarray(x.reshape(b.shape))

    def _product(self, x: np.ndarray) -> np.ndarray:
        """K @ x (N, k), also where only K's upper triangle U is kept: U x + U^T x - D x."""
        K = self._matrix
        if not self._upper:
            return K @ x
        return K @ x + K.T @ x - K.diagonal()[:, None] * x

    def _relative_residual(self, x: np.ndarray, b: np.ndarray) -> float:
        """max over columns of ||K x - b|| / ||b|| (inf for a nonzero residual of b = 0)."""
        if not np.isfinite(x).all():
            return float("inf")
        residual = np.linalg.norm(self._product(x) - b, axis=0)
        norm_b = np.linalg.norm(b, axis=0)
        relative = np.where(norm_b > 0, residual / np.where(norm_b > 0, norm_b, 1.0),
                            np.where(residual > 0, np.inf, 0.0))
        return float(relative.max())

    def _raise_if_inaccurate(self, x: np.ndarray, residual: float) -> None:
        """Raise :class:`SingularSystemError` unless ``x`` is finite and its relative
        residual is within :data:`RESIDUAL_TOLERANCE`."""
        if not np.isfinite(x).all():
            raise SingularSystemError(
                f"{self.backend}: the solution is not finite; the matrix is singular or not "
                "positive definite")
        if not residual <= RESIDUAL_TOLERANCE:  # also catches NaN
            raise SingularSystemError(
                f"{self.backend}: relative residual ||Kx - b|| / ||b|| = {residual:.3g} "
                f"exceeds {RESIDUAL_TOLERANCE:g}; the matrix is singular, not positive "
                "definite or too ill-conditioned")

    def __repr__(self) -> str:
        return (f"Factorization(backend={self.backend!r}, size={self.size}, "
                f"nnz={self._matrix.nnz}, analysis={self.analysis!r})")

    def __getstate__(self) -> dict[str, Any]:
        """Pickle the backend name and the matrix, never the native factor."""
        K = self._matrix
        return {"backend": self.backend, "shape": K.shape,
                "indptr": K.indptr, "indices": K.indices, "data": K.data,
                "groups": self._groups, "upper": self._upper}

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Unpickle by factorizing the matrix again with the same backend."""
        matrix = sp.csr_array((state["data"], state["indices"], state["indptr"]),
                              shape=state["shape"])
        backend = resolve_backend(state["backend"])
        upper = state.get("upper", False)
        if upper and backend != "pardiso":
            matrix, upper = _symmetric_from_upper(matrix), False
        self.__init__(matrix, backend, state.get("groups"), upper)  # type: ignore[misc]


def _symmetric_from_upper(U: sp.csr_array) -> sp.csr_array:
    """The symmetric matrix (canonical CSR, int32 indices) whose upper triangle is ``U``."""
    K = sp.csr_array(U + U.T - sp.diags_array(U.diagonal()))
    K.sum_duplicates()
    K.indptr = K.indptr.astype(np.int32, copy=False)
    K.indices = K.indices.astype(np.int32, copy=False)
    return K


def factorize(matrix: sp.spmatrix | sp.sparray, backend: str = "auto",
              assume_symmetric: bool = False, groups: Any = None,
              triangle: str = "full") -> Factorization:
    """Factorize a sparse symmetric positive definite matrix for repeated solves.

    ``matrix``: (N, N) real, any scipy.sparse format (matrix or array); it is copied
    (as float64 CSR), so later changes to it do not affect the factorization. It must be
    symmetric to 1e-10 relative to its largest entry (each backend reads the triangle it
    needs); ``assume_symmetric=True`` skips that check (for matrices symmetric by
    construction, such as ``A^T W A``). ``backend``: one of :data:`BACKENDS` or ``"auto"``
    (:func:`default_backend`). ``groups``: optional (N,) int ordering hint, the group of
    each unknown, where the unknowns of a group couple with the same others (a vertex's
    or a face frame's coordinates): PARDISO then computes its fill-reducing ordering on
    the compressed graph (one node per group; about half the analysis time on the
    reconstruction system, and no more fill) instead of the whole pattern. Only the
    ordering depends on it, never the solution; other backends ignore it. The price: PARDISO
    given an ordering makes a classic factor instead of its two-level one, whose solves are
    1.3-1.5x faster (``bench/drag_regression.py``); so give ``groups`` for a factorization
    solved once or a few times, not for one solved per frame (the ``Deformer``).

    Raises ``ValueError`` (unknown backend name; non-square or non-symmetric matrix;
    ``groups`` not N integers in [0, N)),
    :class:`SingularSystemError` (non-finite entries), :class:`BackendUnavailableError`
    (known backend not installed),
    ``TypeError`` (not a real sparse matrix) and :class:`SingularSystemError` (the
    backend found the matrix singular or not positive definite; others are only detected
    by :meth:`Factorization.solve`).

    ``triangle="upper"``: ``matrix`` holds only the upper triangle of the symmetric matrix,
    every diagonal entry stored (explicit zeros included), as a canonical CSR array
    (sorted, no duplicates) -- e.g. a Gauss-Newton matrix assembled straight into that
    pattern. PARDISO then reads it without a copy; other backends symmetrize it.
    """
    name = resolve_backend(backend)
    if triangle == "upper":
        return Factorization(_upper_csr(matrix), name,
                             _ordering_groups(groups, matrix.shape[0]), upper=True)
    if triangle != "full":
        raise ValueError(f"triangle must be 'full' or 'upper', got {triangle!r}")
    K = _canonical_matrix(matrix, assume_symmetric)
    return Factorization(K, name, _ordering_groups(groups, K.shape[0]))


def _upper_csr(matrix: Any) -> sp.csr_array:
    """A validated upper-triangular canonical float64 CSR (int32 indices), uncopied when
    it already is one; raises like :func:`_canonical_matrix` (and ``ValueError`` for an
    entry below the diagonal or a missing diagonal entry)."""
    if not (isinstance(matrix, sp.csr_array) and matrix.dtype == np.float64
            and matrix.has_canonical_format):
        matrix = _canonical_matrix(matrix, assume_symmetric=True)
    n = matrix.shape[0]
    if matrix.ndim != 2 or matrix.shape[1] != n:
        raise ValueError(f"matrix must be square, got shape {matrix.shape}")
    indptr = matrix.indptr.astype(np.int32, copy=False)
    indices = matrix.indices.astype(np.int32, copy=False)
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(indptr))
    if (indices < rows).any():
        raise ValueError("triangle='upper' but the matrix has entries below the diagonal")
    if np.count_nonzero(indices == rows) != n:
        raise ValueError("triangle='upper' needs every diagonal entry stored")
    if not np.isfinite(matrix.data).all():
        raise SingularSystemError("matrix has non-finite (NaN or infinite) entries: the "
                                  "input values overflow double precision")
    return sp.csr_array((matrix.data, indices, indptr), shape=matrix.shape)


def _ordering_groups(groups: Any, n: int) -> np.ndarray | None:
    """Validated ``groups`` hint of :func:`factorize`: (n,) int64 in [0, n), or None."""
    if groups is None:
        return None
    g = np.asarray(groups)
    if g.shape != (n,) or (n and g.dtype.kind not in "iu"):
        raise ValueError(f"groups must be {n} integers (one per unknown), got shape "
                         f"{g.shape} and dtype {g.dtype}")
    g = g.astype(np.int64)
    if n and (g.min() < 0 or g.max() >= n):
        raise ValueError(f"groups must lie in [0, {n}), got [{g.min()}, {g.max()}]")
    return g if n else None
