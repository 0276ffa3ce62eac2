"""Intel oneMKL PARDISO through ``ctypes``: the library, one handle, and the SPD solver.

The solver (:class:`PardisoSolver`) factorizes a real SPD matrix (``mtype=2``) from its
upper triangle in zero-based CSR, so the factor stays inside MKL between solves and
nothing is copied per solve. Its analysis (ordering and symbolic factorization) is kept per
sparsity pattern by :mod:`solver.linalg.analysis_cache`; an ordering hint (``groups``) makes
PARDISO order a compressed graph instead (:func:`group_ordering`).
"""

from __future__ import annotations

import ctypes
import functools
import glob
import hashlib
import os
import sys
import time
import weakref

import numpy as np
import scipy.sparse as sp

from . import analysis_cache
from .errors import SingularSystemError

PARDISO_ERRORS: dict[int, str] = {
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
"""PARDISO's error codes and what they mean (MKL reference)."""

MTYPE_SPD = 2
"""PARDISO's matrix type of a real symmetric positive definite matrix."""

IPARM: dict[int, int] = {
    7: 0,  # no iterative refinement: solves are 2-4x cheaper; the residual check guards
    18: 0,  # do not count flops (pardisoinit asks for it; costs analysis time)
    23: 1,  # two-level factorization: faster solves and no slower factorization here
    34: 1,  # zero-based ia/ja, so scipy's CSR arrays are passed as they are
}
"""Zero-based entries of MKL's ``iparm`` set on top of ``pardisoinit()``'s defaults for
``mtype=2`` (which already select the parallel nested-dissection ordering, ``iparm[1]=3``)."""


class _Mkl:
    """The ``libmkl_rt`` entry points PARDISO needs, loaded once per process.

    Args:
        lib: the loaded ``libmkl_rt``.

    Raises:
        ImportError: the library uses the ILP64 (64-bit integer) interface.
        AttributeError: the library lacks the PARDISO entry points.
    """

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
        self._max_threads = lib.MKL_Get_Max_Threads
        self._max_threads.argtypes = []
        self._max_threads.restype = ctypes.c_int

    def max_threads(self) -> int:
        """The OpenMP threads MKL would use now in the calling thread
        (``mkl_get_max_threads``: ``MKL_NUM_THREADS``, or ``mkl_set_num_threads`` since)."""
        return int(self._max_threads())


@functools.cache
def load_mkl() -> _Mkl:
    """Load ``libmkl_rt`` once per process.

    Looks where pip's ``mkl`` wheel puts it (``<sys.prefix>/lib``) or at
    ``$PYPARDISO_MKL_RT``; only if that fails, imports :mod:`pypardiso` and uses the
    library its (slower, recursive) search found.

    Returns:
        The library's PARDISO entry points.

    Raises:
        ImportError: the library cannot be found or loaded.
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


class PardisoHandle:
    """One PARDISO handle (``pt``, ``iparm`` and the ordering ``perm``) and its MKL memory.

    Exactly one owner uses a handle at a time (a live solver, or the analysis cache while it
    is idle), so no lock is needed around its calls. With ``perm`` given, PARDISO uses that
    ordering (``iparm[4] = 1``). Else it orders the matrix itself, and returns its ordering
    in ``perm`` only if ``return_ordering`` (``iparm[4] = 2``). Either user-permutation mode
    silently turns the two-level factorization (``iparm[23] = 1``) into the classic one,
    whose solves cost 1.3-1.5x more (bench/drag_regression.py): only a handle with neither
    keeps the two-level factor.

    Args:
        mkl: the library (:func:`load_mkl`).
        n: order N of the matrix.
        perm: (N,) int32 zero-based fill-reducing ordering to use, or None.
        return_ordering: without ``perm``, have PARDISO return its ordering in ``perm``.
        single: factorize and solve in single precision (``iparm[27] = 1``): the values,
            right-hand sides and solutions passed to :meth:`call` are then float32.
    """

    def __init__(self, mkl: _Mkl, n: int, perm: np.ndarray | None,
                 return_ordering: bool = False, single: bool = False) -> None:
        self.mkl = mkl
        self.n = n
        self.pt = np.zeros(64, dtype=np.int64)  # opaque handle: must never be touched
        self.iparm = np.zeros(64, dtype=np.int32)
        mtype = ctypes.c_int32(MTYPE_SPD)
        mkl.pardisoinit(self.pt.ctypes.data, ctypes.byref(mtype), self.iparm.ctypes.data)
        for index, value in IPARM.items():
            self.iparm[index] = value
        self.iparm[27] = int(single)  # 1: float32 values, right-hand sides and solutions
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
        """Run one PARDISO phase on an upper-triangle CSR matrix.

        Args:
            phase: PARDISO's phase (11 analysis, 22 numerical factorization, 33 solve,
                0 free the factor, -1 free everything).
            a, ia, ja: (nnz,) float64 values (float32 for a ``single`` handle), (N + 1,)
                int32 row pointers and (nnz,) int32 column indices of the upper triangle,
                zero-based.
            b, x: (N, nrhs) float64 (float32) column-major right-hand sides and solutions
                (phase 33).
            nrhs: number of right-hand sides.

        Returns:
            PARDISO's error code (0 on success, see :data:`PARDISO_ERRORS`).
        """
        one = ctypes.c_int32(1)
        err = ctypes.c_int32(0)
        self.mkl.pardiso(
            self.pt.ctypes.data, ctypes.byref(one), ctypes.byref(one),
            ctypes.byref(ctypes.c_int32(MTYPE_SPD)), ctypes.byref(ctypes.c_int32(phase)),
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


def upper_triangle(K: sp.csr_array) -> sp.csr_array:
    """The upper triangle PARDISO reads, every diagonal entry stored.

    Args:
        K: (N, N) canonical float64 CSR, int32 indices.

    Returns:
        (N, N) CSR upper triangle of ``K``, sorted int32 indices, with every diagonal entry
        stored (explicitly zero if need be: PARDISO requires them).
    """
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


def pattern_key(n: int, ia: np.ndarray, ja: np.ndarray, hinted: bool,
                single: bool = False, threads: int = 1) -> bytes:
    """The analysis cache's key of an upper-triangle CSR pattern and the PARDISO settings.

    Args:
        n: order of the matrix.
        ia, ja: (n + 1,) and (nnz,) int32 row pointers and column indices.
        hinted: ordered from a ``groups`` hint (classic factor) rather than by PARDISO
            (two-level factor).
        single: a single-precision handle (its analysis is not shared with double's).
        threads: MKL's thread count at the analysis (:meth:`_Mkl.max_threads`). The
            symbolic factorization plans the parallel factorization for it: an analysis
            made with 1 thread and factorized with 2 fails with error -4 ("not positive
            definite") on an SPD matrix (the mkl 2026.2 wheel, a 99K-unknown reconstruction system;
            ``tests/solver/test_analysis_cache_threads.py``), so an analysis is reused
            only at the thread count it was made with.

    Returns:
        A 128-bit digest.
    """
    digest = hashlib.blake2b(digest_size=16)
    digest.update(repr((n, len(ja), hinted, single, threads,
                        sorted(IPARM.items()))).encode())
    digest.update(memoryview(ia))
    digest.update(memoryview(ja))
    return digest.digest()


def _compressed_pattern(ia: np.ndarray, ja: np.ndarray, groups: np.ndarray,
                        n_groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The graph with one node per group, as an SPD matrix PARDISO can order.

    Nodes ``g`` and ``h`` are joined where some unknown of ``g`` couples with one of ``h``.
    The values make it diagonally dominant; they must be nonzero, since PARDISO's ordering
    skips explicitly stored zeros (measured: zero values gave nearly no fill reduction).

    Args:
        ia, ja: upper-triangle CSR pattern of an (N, N) matrix (int32).
        groups: (N,) int64 group of each unknown.
        n_groups: number of groups.

    Returns:
        Upper-triangle CSR ``(a, ia, ja)``: float64 values and int32 index arrays.
    """
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


def group_ordering(mkl: _Mkl, ia: np.ndarray, ja: np.ndarray,
                   groups: np.ndarray) -> np.ndarray:
    """Fill-reducing ordering of the unknowns from PARDISO's ordering of their groups.

    PARDISO orders the compressed graph (one node per group, :func:`_compressed_pattern`);
    the unknowns of each group stay together, in the order of their group (PARDISO's
    ``perm`` lists old indices by new position). The compressed graph has a fraction of the
    nodes and edges, so its nested dissection costs a fraction of the full one's.

    Args:
        mkl: the library (:func:`load_mkl`).
        ia, ja: upper-triangle CSR pattern of the (N, N) matrix (int32).
        groups: (N,) int64 group of each unknown, in [0, N).

    Returns:
        (N,) int32 ordering (old index of each new position).

    Raises:
        RuntimeError: PARDISO failed to order the compressed graph.
    """
    n_groups = int(groups.max()) + 1
    a, cia, cja = _compressed_pattern(ia, ja, groups, n_groups)
    handle = PardisoHandle(mkl, n_groups, None, return_ordering=True)
    try:
        error = handle.call(11, a, cia, cja)
        if error:
            raise RuntimeError(f"PARDISO ordering of the compressed graph failed: error "
                               f"{error} ({PARDISO_ERRORS.get(error, '?')})")
        position = np.empty(n_groups, dtype=np.int64)
        position[handle.perm] = np.arange(n_groups)
    finally:
        handle.release()
    return np.argsort(position[groups], kind="stable").astype(np.int32)


def analyze_upper(triangle: sp.csr_array, single: bool = False) -> bool:
    """Compute and cache PARDISO's analysis (ordering and symbolic factorization) of an
    upper-triangle pattern without factorizing, so that the first factorization of that
    pattern pays only its numerical phase (e.g. an interactive session's first refined
    drag). Only the pattern is read: the values may be anything.

    Args:
        triangle: (N, N) canonical CSR upper triangle, every diagonal entry stored.
        single: for single-precision factorizations (``PardisoSolver(single=True)``).

    Returns:
        True where an analysis was computed; False where the cache already had the pattern
        or is disabled (``ANALYSIS_CACHE_BYTES = 0``).

    Raises:
        ImportError: MKL cannot be loaded.
        MemoryError, RuntimeError: PARDISO failed to analyse the pattern (as
            :class:`PardisoSolver` reports its failures).
    """
    if analysis_cache.ANALYSIS_CACHE_BYTES <= 0:
        return False
    n = int(triangle.shape[0])
    ia = np.ascontiguousarray(triangle.indptr, dtype=np.int32)
    ja = np.ascontiguousarray(triangle.indices, dtype=np.int32)
    mkl = load_mkl()
    key = pattern_key(n, ia, ja, False, single, mkl.max_threads())
    handle, perm = analysis_cache.CACHE.acquire(key)
    if handle is not None:  # an idle analysed handle: give it back untouched
        analysis_cache.CACHE.park(key, handle)
        return False
    handle = PardisoHandle(mkl, n, perm, single=single)
    values = np.zeros(len(ja), dtype=np.float32 if single else np.float64)
    values[ia[:-1]] = 1.0  # each row starts at its diagonal entry
    PardisoSolver._raise_if_failed(handle, handle.call(11, values, ia, ja))
    analysis_cache.CACHE.remember(key, handle.perm)
    analysis_cache.CACHE.park(key, handle)
    return True


def _retire(handle: PardisoHandle, key: bytes) -> None:
    """Finalizer of a PARDISO solver: give its analysis to the cache, or free it."""
    if analysis_cache.ANALYSIS_CACHE_BYTES > 0:
        analysis_cache.CACHE.park(key, handle)
    else:
        handle.release()


class PardisoSolver:
    """MKL PARDISO factor of an SPD matrix, from its upper triangle.

    A matrix whose pattern the analysis cache knows reuses an idle handle (numerical
    factorization only) or the kept ordering; else the analysis is computed, on the
    compressed graph of ``groups`` when given (:func:`group_ordering`).

    Args:
        matrix: (N, N) canonical float64 CSR, symmetric (with ``upper``, only its upper
            triangle, every diagonal entry stored).
        groups: optional (N,) int64 ordering hint: unknowns that always couple alike (e.g.
            the three unknowns of one face frame).
        upper: ``matrix`` is the upper triangle already.
        single: factorize a float32 copy of the values and solve in float32 (MKL's
            ``iparm[27] = 1``): about half the factorization time on the refinement's
            Gauss-Newton matrix, with relative residuals ~1e-7 x its condition instead of
            1e-16 x; the solutions are returned as float64.

    Attributes:
        analysis: ``"cached"`` or ``"computed"``.
        timings: seconds of ``"analysis"`` (ordering and symbolic factorization) and
            ``"factorization"``.

    Raises:
        ImportError: MKL cannot be loaded.
        SingularSystemError: a zero or negative pivot (not positive definite).
        MemoryError: PARDISO ran out of memory.
        RuntimeError: any other PARDISO error.
    """

    def __init__(self, matrix: sp.csr_array, groups: np.ndarray | None = None,
                 upper: bool = False, single: bool = False) -> None:
        mkl = load_mkl()
        triangle = matrix if upper else upper_triangle(matrix)
        self.n = int(triangle.shape[0])
        # PARDISO reads these arrays in every phase: keep them alive and unchanged.
        self._ia = np.ascontiguousarray(triangle.indptr, dtype=np.int32)
        self._ja = np.ascontiguousarray(triangle.indices, dtype=np.int32)
        self._dtype = np.float32 if single else np.float64
        self._a = np.ascontiguousarray(triangle.data, dtype=self._dtype)
        key = pattern_key(self.n, self._ia, self._ja, groups is not None, single,
                          mkl.max_threads())
        caching = analysis_cache.ANALYSIS_CACHE_BYTES > 0
        handle, perm = analysis_cache.CACHE.acquire(key) if caching else (None, None)
        reused = handle is not None
        self.analysis = "cached" if reused or perm is not None else "computed"
        start = time.perf_counter()
        if handle is None:
            if perm is None and groups is not None:
                perm = group_ordering(mkl, self._ia, self._ja, groups)
            handle = PardisoHandle(mkl, self.n, perm, single=single)
            error = handle.call(11, self._a, self._ia, self._ja)  # ordering + symbolic
            self._raise_if_failed(handle, error)
            if self.analysis == "computed" and analysis_cache.ANALYSIS_CACHE_BYTES > 0:
                analysis_cache.CACHE.remember(key, handle.perm)
        analysed = time.perf_counter()
        self._handle = handle
        self._raise_if_failed(handle, handle.call(22, self._a, self._ia, self._ja))
        handle.factored = True
        self.timings = {"analysis": 0.0 if reused else analysed - start,
                        "factorization": time.perf_counter() - analysed}
        self._finalizer = weakref.finalize(self, _retire, handle, key)

    @staticmethod
    def _raise_if_failed(handle: PardisoHandle, error: int) -> None:
        """Free ``handle`` and raise if PARDISO reported ``error`` != 0."""
        if not error:
            return
        handle.release()
        message = (f"PARDISO factorization failed: error {error} "
                   f"({PARDISO_ERRORS.get(error, '?')})")
        if error in (-4, -7):
            raise SingularSystemError(message)
        if error == -2:
            raise MemoryError(message)
        raise RuntimeError(message)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Forward and back substitution.

        Args:
            rhs: (N, k) float64.

        Returns:
            (N, k) float64 solutions (column-major; computed in float32 by a ``single``
            solver).

        Raises:
            RuntimeError: PARDISO reported an error.
        """
        b = np.asfortranarray(rhs, dtype=self._dtype)  # PARDISO wants column-major columns
        x = np.zeros_like(b, order="F")
        error = self._handle.call(33, self._a, self._ia, self._ja, b, x, b.shape[1])
        if error:
            raise RuntimeError(f"PARDISO solve failed: error {error} "
                               f"({PARDISO_ERRORS.get(error, '?')})")
        return x.astype(np.float64, order="F", copy=False)
