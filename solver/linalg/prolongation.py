r"""Energy-minimizing prolongators computed in place: pyamg's ``energy`` smoothing in a
third of its memory.

Smoothed aggregation with ``smooth=("energy", {...})`` (Mandel, Brezina and Vaněk 1999;
Olson, Schroder and Tuminaro 2011) improves each tentative prolongator ``T`` (N, M) by a few
iterations of CG on ``A T = 0``, restricted to a sparsity pattern (``T``'s grown by one
product with the strength graph) and keeping ``T B_c = B_f`` (the near-null space). pyamg
(``pyamg.aggregation.smooth.cg_prolongation_smoothing``) runs that CG on sparse matrices:
every update (``T + alpha P``, ``R - alpha AP``, ``Z + beta P``, the products of the Frobenius
inner products, the pattern's own values) makes a new matrix of the pattern's size with its
own index arrays, about ten at once. That transient is the refinement's memory peak
(docs/large-meshes.md): 240 MB above what is live at the 100K-face scan's first level,
~3.8 GB at 1.6M faces.

:func:`energy_prolongator` is the same iteration on the pattern's value arrays: ``T``, the
residual ``R``, the search direction ``P`` and ``A P`` share one pair of index arrays and
are updated in place, block by block (the preconditioned residual ``Z = D^-1 R`` is never
stored). The arithmetic is pyamg's (its kernels ``incomplete_mat_mult_bsr`` and
``satisfy_constraints`` do the products and the projection; Jacobi's row scaling is the
``local`` (Gershgorin) or ``diagonal`` weighting); the Frobenius inner products are summed
in double precision (pyamg sums in the matrices' precision), so the prolongators agree with
pyamg's to the rounding of that precision (``tests/solver/test_prolongation.py``). Options
it does not cover (root nodes, filtering, other Krylov methods) are handed to pyamg's.

:func:`jacobi_prolongator` is pyamg's Jacobi smoothing (``local`` weighting) without its
copies of the matrix. :func:`solver.linalg.hierarchy.smoothed_aggregation` sets hierarchies
up with both.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from .blocked import (
    RUN_VALUES,
    axpy,
    block_pattern,
    leading_blocks,
    row_runs,
    run_block_rows,
    shrunk,
)


def _pyamg_energy(*args: Any, **kwargs: Any) -> sp.bsr_array:
    """pyamg's own ``energy_prolongation_smoother``."""
    from pyamg.aggregation import smooth

    return smooth.energy_prolongation_smoother(*args, **kwargs)


def energy_prolongator(A: sp.spmatrix, T: sp.spmatrix, Atilde: sp.csr_array, B: np.ndarray,
                       Bf: np.ndarray | None, Cpt_params: tuple[bool, dict],
                       krylov: str = "cg", maxiter: int = 4, tol: float = 1e-8,
                       degree: int = 1, weighting: str = "local",
                       prefilter: dict | None = None,
                       postfilter: dict | None = None) -> sp.bsr_array:
    """pyamg's ``energy_prolongation_smoother`` (same signature and answer), in place.

    Args:
        A: (N, N) SPD CSR or BSR matrix (blocks (b, b)).
        T: (N, M) CSR or BSR tentative prolongator (row blocks of A's).
        Atilde: (N / b, N / b) CSR strength graph (its pattern grows T's).
        B: (M, k) near-null modes of the coarse level.
        Bf: (N, k) those of the fine level (pyamg's; unused here).
        Cpt_params, krylov, maxiter, tol, degree, weighting, prefilter, postfilter: as
            pyamg's; anything but ``krylov="cg"``, no root nodes, no filters, ``degree``
            >= 1 and ``weighting`` ``"local"`` or ``"diagonal"`` goes to pyamg's function.

    Returns:
        (N, M) BSR prolongator, T's blocks, on the grown pattern (zero blocks dropped).

    Example:
        >>> import numpy as np, scipy.sparse as sp
        >>> from pyamg.gallery import poisson
        >>> A = poisson((6,), format="csr")
        >>> T = sp.csr_array(np.kron(np.eye(2), np.ones((3, 1))))
        >>> P = energy_prolongator(A, T, A, np.ones((2, 1)), None, (False, {}))
        >>> np.round(P.toarray()[2], 4).tolist()
        [0.6667, 0.3333]
    """
    supported = (krylov == "cg" and not Cpt_params[0] and not prefilter and not postfilter
                 and degree >= 1 and weighting in ("local", "diagonal"))
    if not supported:
        return _pyamg_energy(A, T, Atilde, B, Bf, Cpt_params, krylov=krylov, maxiter=maxiter,
                             tol=tol, degree=degree, weighting=weighting, prefilter=prefilter,
                             postfilter=postfilter)
    from pyamg import amg_core
    from pyamg.aggregation.smooth import satisfy_constraints
    from pyamg.util.utils import compute_BtBinv

    if maxiter < 0:
        raise ValueError("maxiter must be > 0")
    A = A.tobsr(blocksize=(1, 1), copy=False) if A.format == "csr" else A
    T = T.tobsr(blocksize=(1, 1), copy=False) if T.format == "csr" else T
    if min(T.nnz, A.nnz) == 0:
        return T
    rb, cb = T.blocksize
    full_shape = T.shape
    indptr, indices = _grown_pattern(T, Atilde, degree)
    shape, dtype = (len(indices), rb, cb), T.dtype
    n_block_rows, n_block_cols = T.shape[0] // rb, T.shape[1] // cb

    def on_pattern(values: np.ndarray) -> sp.bsr_array:  # a view: the shared index arrays
        return sp.bsr_array((values, indices, indptr), shape=full_shape, copy=False)

    def times_a(P_values: np.ndarray, out: np.ndarray) -> None:  # out = (A P) on the pattern
        out.fill(0)
        amg_core.incomplete_mat_mult_bsr(
            A.indptr, A.indices, np.ravel(A.data), indptr, indices, np.ravel(P_values),
            indptr, indices, np.ravel(out), n_block_rows, n_block_cols,
            A.blocksize[0], A.blocksize[1], cb)

    AP = np.zeros(shape, dtype=dtype)
    BtBinv = compute_BtBinv(B, on_pattern(AP))
    scale = _row_scale(A, weighting, dtype)  # (N,) D^-1: Jacobi on the rows
    block_row = np.repeat(np.arange(n_block_rows, dtype=np.int64), np.diff(indptr))
    T_values = _values_on_pattern(T, indptr, indices)
    R = np.empty(shape, dtype=dtype)
    times_a(T_values, R)  # R = -A T on the pattern (T's values lie on it)
    np.negative(R, out=R)
    satisfy_constraints(on_pattern(R), B, BtBinv)
    del T
    P = np.zeros(shape, dtype=dtype)
    previous = 0.0
    for i in range(maxiter):
        rz = _scaled_inner(R, scale, block_row)  # <R, D^-1 R>_F
        if rz < tol:
            break
        _new_direction(P, R, scale, block_row, rz / previous if i else 0.0)
        previous = rz
        times_a(P, AP)
        satisfy_constraints(on_pattern(AP), B, BtBinv)
        alpha = rz / _inner(P, AP)
        axpy(T_values, P, alpha)      # T += alpha P
        axpy(R, AP, -alpha)           # R -= alpha A P
    del R, P, AP
    # the pattern's arrays are this function's own
    return _without_zero_blocks(T_values, indices, indptr, full_shape)


def jacobi_prolongator(A: sp.spmatrix, T: sp.spmatrix,
                       omega: float = 4.0 / 3.0) -> sp.bsr_array:
    """pyamg's ``jacobi_prolongation_smoother`` with ``weighting="local"``, degree 1 and no
    filtering, in place: ``P = T - omega D^-1 A T`` with ``D`` each row's Gershgorin bound
    (the sum of its absolute values).

    pyamg scales a copy of ``A`` by ``D^-1``, multiplies that copy by ``omega`` (a second
    copy), forms the product with ``T`` and subtracts it from ``T`` (two more matrices of
    the prolongator's size). Here ``A T`` is computed once on its own pattern (pyamg's
    ``incomplete_mat_mult_bsr``; the pattern is A's times T's, so nothing of the product is
    dropped) and ``T - omega D^-1 (A T)`` is written over it in runs of block rows (each
    run's temporaries ~1 MB), its zero blocks then dropped in place.

    Args:
        A: (N, N) CSR or BSR matrix (blocks (b, b)).
        T: (N, M) CSR or BSR tentative prolongator (row blocks of A's).
        omega: the Jacobi weight (pyamg's default 4/3).

    Returns:
        (N, M) BSR prolongator with T's blocks, exact zeros dropped (pyamg's answer to the
        rounding of A's precision, ``tests/solver/test_hierarchy.py``).

    Example:
        >>> import numpy as np, scipy.sparse as sp
        >>> from pyamg.gallery import poisson
        >>> A = poisson((6,), format="csr")
        >>> T = sp.csr_array(np.kron(np.eye(2), np.ones((3, 1))))
        >>> P = jacobi_prolongator(A, T)
        >>> np.round(P.toarray()[:3, 0], 4).tolist()
        [0.5556, 1.0, 0.6667]
    """
    from pyamg import amg_core

    A = A.tobsr(blocksize=(1, 1), copy=False) if A.format == "csr" else A
    T = T.tobsr(blocksize=(1, 1), copy=False) if T.format == "csr" else T
    if min(T.nnz, A.nnz) == 0:
        return sp.bsr_array(T)
    rb, cb = T.blocksize
    n_block_rows, n_block_cols = T.shape[0] // rb, T.shape[1] // cb
    indptr, indices = _grown_pattern(T, block_pattern(A), 1)
    values = np.zeros((len(indices), rb, cb), dtype=np.result_type(A.dtype, T.dtype))
    amg_core.incomplete_mat_mult_bsr(
        A.indptr, A.indices, np.ravel(A.data), T.indptr, T.indices, np.ravel(T.data),
        indptr, indices, np.ravel(values), n_block_rows, n_block_cols,
        A.blocksize[0], A.blocksize[1], cb)
    scale = _row_scale(A, "local", values.dtype) * values.dtype.type(-omega)
    for rows, entries in row_runs(indptr):  # values = T - omega D^-1 (A T), in place
        block_row = run_block_rows(indptr, rows)
        values[entries] *= scale[block_row[:, None] * rb + np.arange(rb)][:, :, None]
        _add_rows_on_pattern(values, T, indptr, indices, rows, entries)
    return _without_zero_blocks(values, indices, indptr, T.shape)


def _grown_pattern(T: sp.bsr_array, Atilde: sp.csr_array,
                   degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Block-row pointers and sorted block columns of ``Atilde^degree`` times T's block
    pattern (pyamg's ``pattern``), without its values."""
    T.sort_indices()
    pattern, strength = block_pattern(T), block_pattern(Atilde)
    for _ in range(degree):
        pattern = strength @ pattern
    pattern.sort_indices()
    return pattern.indptr, pattern.indices


def _values_on_pattern(T: sp.bsr_array, indptr: np.ndarray,
                       indices: np.ndarray) -> np.ndarray:
    """(nnz_blocks, rb, cb) T's blocks scattered onto the (larger) pattern ``indptr``,
    ``indices`` (both sorted by row then column; T's pattern lies inside it)."""
    values = np.zeros((len(indices), *T.blocksize), dtype=T.dtype)
    for rows, entries in row_runs(indptr):
        _add_rows_on_pattern(values, T, indptr, indices, rows, entries)
    return values


def _add_rows_on_pattern(values: np.ndarray, T: sp.bsr_array, indptr: np.ndarray,
                         indices: np.ndarray, rows: slice, entries: slice) -> None:
    """values[entries] += T's blocks of the block rows ``rows`` (T's pattern inside the
    pattern ``indptr``, ``indices``, both sorted by row then column)."""
    lo, hi = int(T.indptr[rows.start]), int(T.indptr[rows.stop])
    if hi == lo:
        return
    n_cols = np.int64(T.shape[1] // T.blocksize[1])
    wide = run_block_rows(indptr, rows) * n_cols
    wide += indices[entries]
    own = run_block_rows(T.indptr, rows) * n_cols
    own += T.indices[lo:hi]
    values[entries][np.searchsorted(wide, own)] += T.data[lo:hi]


def _without_zero_blocks(values: np.ndarray, indices: np.ndarray, indptr: np.ndarray,
                         shape: tuple[int, int]) -> sp.bsr_array:
    """The BSR matrix of ``values`` (nnz_blocks, rb, cb) on the pattern ``indptr``,
    ``indices`` without its all-zero blocks (scipy's ``eliminate_zeros``), compacted in
    place run by run and the arrays shrunk where they are (scipy's makes a mask, the kept
    blocks' positions and a copy of the kept values). The three arrays are overwritten:
    the caller's own, with no other view of them in use."""
    counts = np.zeros(len(indptr) - 1, dtype=indptr.dtype)
    kept = 0
    for rows, entries in row_runs(indptr):
        if entries.stop == entries.start:
            continue
        keep = values[entries].reshape(entries.stop - entries.start, -1).any(axis=1)
        n = int(np.count_nonzero(keep))
        values[kept:kept + n] = values[entries][keep]  # kept <= entries.start: no overlap
        indices[kept:kept + n] = indices[entries][keep]
        counts[rows] = np.bincount(run_block_rows(indptr, rows)[keep] - rows.start,
                                   minlength=rows.stop - rows.start)
        kept += n
    indptr[0] = 0
    np.cumsum(counts, out=indptr[1:])
    del counts
    return sp.bsr_array((shrunk(values, kept), shrunk(indices, kept), indptr), shape=shape,
                        copy=False)


def _row_scale(A: sp.bsr_array, weighting: str, dtype: np.dtype) -> np.ndarray:
    """(N,) the Jacobi scaling of each row: 1 / sum_j |a_ij| (``local``, Gershgorin) or
    1 / |a_ii| (``diagonal``); 0 where that is 0. Summed block by block (no copy of A)."""
    n_rows = A.shape[0]
    rb, cb = A.blocksize
    if weighting == "diagonal":
        size = np.abs(A.diagonal()).astype(dtype)
    else:  # block rows in runs of about RUN_VALUES values: no per-entry temporaries
        size = np.zeros((n_rows // rb, rb), dtype=np.float64)
        indptr = A.indptr
        for rows, entries in row_runs(indptr, RUN_VALUES // (rb * cb)):
            first, last, lo, hi = rows.start, rows.stop, entries.start, entries.stop
            if hi == lo:
                continue
            sums = np.zeros((hi - lo + 1, rb))  # each block's row sums, and a zero row
            np.abs(A.data[lo:hi]).sum(axis=2, dtype=np.float64, out=sums[:-1])
            run = np.add.reduceat(sums, indptr[first:last] - lo, axis=0)
            run[np.diff(indptr[first:last + 1]) == 0] = 0.0  # empty block rows
            size[first:last] = run
        size = size.ravel().astype(dtype)
    scale = np.zeros(n_rows, dtype=dtype)
    np.divide(1.0, size, out=scale, where=size != 0)
    return scale


def _row_factors(scale: np.ndarray, block_row: np.ndarray, part: slice,
                 rb: int) -> np.ndarray:
    """(blocks, rb, 1) the scaling of each block's rows."""
    return scale[block_row[part, None] * rb + np.arange(rb)][:, :, None]


def _scaled_inner(R: np.ndarray, scale: np.ndarray, block_row: np.ndarray) -> float:
    """<R, D^-1 R>_F in double precision."""
    total = 0.0
    for part in leading_blocks(R):
        r = R[part]
        total += float(np.einsum("kab,kab->", r * _row_factors(scale, block_row, part,
                                                                 R.shape[1]), r,
                                 dtype=np.float64))
    return total


def _inner(X: np.ndarray, Y: np.ndarray) -> float:
    """<X, Y>_F in double precision."""
    return sum(float(np.einsum("kab,kab->", X[part], Y[part], dtype=np.float64))
               for part in leading_blocks(X))


def _new_direction(P: np.ndarray, R: np.ndarray, scale: np.ndarray, block_row: np.ndarray,
                   beta: float) -> None:
    """P = D^-1 R + beta P, in place."""
    beta = P.dtype.type(beta)
    for part in leading_blocks(P):
        P[part] *= beta
        P[part] += R[part] * _row_factors(scale, block_row, part, R.shape[1])
