r"""Smoothed-aggregation multigrid hierarchies set up in bounded memory: pyamg's
``smoothed_aggregation_solver`` for the options this library uses, level by level with
prolongators computed in place and coarse matrices formed in blocks of rows.

pyamg's setup of one level holds, besides the matrix ``A``: for Jacobi-smoothed
prolongators two scaled copies of ``A`` and two matrices of the prolongator's size (``D^-1 A
T`` and ``T - D^-1 A T``); for energy-minimized ones about ten matrices of the prolongator's
pattern; and for the coarse matrix ``R A P`` the whole product ``R A`` (a matrix of
``A``'s row count times the coarse size, several times the prolongator). On Eq. 5's matrix
these transients are a third of the linear answer's peak memory (docs/large-meshes.md).

:func:`smoothed_aggregation` builds the same levels (the same strength graphs, aggregates,
tentative prolongators and near-null spaces, by pyamg's functions) with
:func:`solver.linalg.prolongation.jacobi_prolongator` or
:func:`~solver.linalg.prolongation.energy_prolongator` and :func:`galerkin_product` (``R A
P`` one block of coarse rows at a time). The answer is pyamg's to the rounding of the
matrix's precision (``tests/solver/test_hierarchy.py``). Options it does not cover are
handed to pyamg's function unchanged.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from .blocked import block_pattern, row_runs
from .prolongation import energy_prolongator, jacobi_prolongator

GALERKIN_BLOCK_VALUES = 1 << 19
"""Stored values of the restriction per block of :func:`galerkin_product`: the block's
``R_J A`` is a few times that (tens of MB in single precision)."""

SUPPORTED_STRENGTH = ("symmetric", "predefined", None)
SUPPORTED_SMOOTHING = ("jacobi", "energy", None)


def smoothed_aggregation(A: sp.spmatrix, B: np.ndarray | None = None, *,
                         strength: Any = "symmetric", smooth: Any = ("jacobi", {}),
                         max_levels: int = 10, max_coarse: int = 10,
                         presmoother: Any = ("block_gauss_seidel", {"sweep": "symmetric"}),
                         postsmoother: Any = ("block_gauss_seidel", {"sweep": "symmetric"}),
                         **options: Any) -> Any:
    """``pyamg.smoothed_aggregation_solver(A, B, symmetry="symmetric", aggregate="standard",
    improve_candidates=None, ...)`` in bounded memory.

    Args:
        A: (N, N) real symmetric CSR or BSR matrix (float32 or float64).
        B: (N, k) near-null space (None: pyamg's constant per block unknown).
        strength: per level (a list) or for all, ``"symmetric"`` (with pyamg's ``theta``),
            ``("predefined", {"C": csr})`` or None (the matrix itself).
        smooth: per level or for all, ``("jacobi", {"weighting": "local", "omega": w})``
            (degree 1, unfiltered; pyamg's default ``diagonal`` weighting is handed to
            pyamg), ``("energy", {...})`` (see
            :func:`~solver.linalg.prolongation.energy_prolongator`) or None.
        max_levels, max_coarse, presmoother, postsmoother: as pyamg's.
        **options: further keywords of pyamg's function (``coarse_solver``; any other, or a
            ``symmetry``, ``aggregate`` or ``improve_candidates`` this does not cover, sends
            the whole call to pyamg's function).

    Returns:
        pyamg's ``MultilevelSolver`` (levels with ``A``, ``B``, ``P``, ``R``).

    Example:
        >>> import numpy as np
        >>> from pyamg.gallery import poisson
        >>> A = poisson((40, 40), format="csr")
        >>> ml = smoothed_aggregation(A, np.ones((1600, 1)), max_coarse=50,
        ...                           smooth=("jacobi", {"weighting": "local"}))
        >>> [level.A.shape[0] for level in ml.levels]
        [1600, 280, 34]
        >>> ml.levels[0].R.format  # a view of the prolongator's arrays
        'csc'
        >>> bool(np.linalg.norm(A @ ml.solve(np.ones(1600), tol=1e-8) - 1) < 1e-6)
        True
    """
    import pyamg
    from pyamg.util.utils import (
        levelize_smooth_or_improve_candidates,
        levelize_strength_or_aggregation,
    )

    if not _supported(A, strength, smooth, options):
        return pyamg.smoothed_aggregation_solver(
            A, B, strength=strength, smooth=smooth, max_levels=max_levels,
            max_coarse=max_coarse, presmoother=presmoother, postsmoother=postsmoother,
            **options)
    for key in ("symmetry", "aggregate", "improve_candidates"):
        options.pop(key, None)
    blocksize = _blocksize(A)
    if B is None:
        B = np.kron(np.ones((A.shape[0] // blocksize, 1), dtype=A.dtype),
                    np.eye(blocksize, dtype=A.dtype))
    B = np.asarray(B, dtype=A.dtype).reshape(A.shape[0], -1)
    strength = list(strength) if isinstance(strength, list) else strength
    max_levels, max_coarse, strengths = levelize_strength_or_aggregation(
        strength, max_levels, max_coarse)
    smoothings = levelize_smooth_or_improve_candidates(smooth, max_levels)
    levels = [pyamg.multilevel.MultilevelSolver.Level()]
    levels[0].A, levels[0].B = A, B
    A.symmetry = "symmetric"
    while (len(levels) < max_levels
           and levels[-1].A.shape[0] // _blocksize(levels[-1].A) > max_coarse):
        depth = len(levels) - 1
        levels.append(_coarser(levels[-1], strengths[depth], smoothings[depth]))
    ml = pyamg.multilevel.MultilevelSolver(levels, **options)
    pyamg.relaxation.smoothing.change_smoothers(ml, presmoother, postsmoother)
    return ml


def _coarser(fine: Any, strength: Any, smooth: Any) -> Any:
    """The next level below ``fine`` (its ``P`` and ``R`` set): pyamg's ``_extend_hierarchy``
    for the supported options."""
    import pyamg
    from pyamg.aggregation.aggregate import standard_aggregation
    from pyamg.aggregation.tentative import fit_candidates
    from pyamg.strength import symmetric_strength_of_connection

    A = fine.A
    kind, kwargs = _unpack(strength)
    if kind == "symmetric":
        C = symmetric_strength_of_connection(A, **kwargs)
    elif kind == "predefined":
        C = kwargs["C"].tocsr()
    else:
        C = A.tocsr()
    aggregates, _ = standard_aggregation(C)
    T, B = fit_candidates(aggregates, fine.B)
    del aggregates
    kind, kwargs = _unpack(smooth)
    if kind == "jacobi":
        P = jacobi_prolongator(A, T, omega=kwargs.get("omega", 4.0 / 3.0))
    elif kind == "energy":
        P = energy_prolongator(A, T, C, B, None, (False, {}), **kwargs)
    else:
        P = T
    del C, T
    fine.P, fine.R = P, P.T
    coarse = pyamg.multilevel.MultilevelSolver.Level()
    coarse.A, coarse.B = galerkin_product(fine.R, A, P), B
    coarse.A.symmetry = "symmetric"  # as pyamg marks its levels
    if P.format == "bsr" and P.blocksize[0] == 1:
        fine.R = None  # let go before the prolongator's CSR indices are made
        fine.P = _scalar_rows(P)
        fine.R = fine.P.T  # CSC: a view of the same arrays, not a copy
    return coarse


def _scalar_rows(P: sp.bsr_array) -> sp.csr_array:
    """A prolongator with (1, c) blocks as CSR sharing its values (the blocks' values are
    already in CSR order): its transpose is then a free CSC view, where pyamg stores ``R =
    P^T`` as a second BSR matrix (20 bytes per block). On Eq. 5's matrix at 100K faces (a
    scratch probe, not a bench/ command): the same cycle to the bit, 15 % faster (0.136
    against 0.160 s per W-cycle); the linear answer's CPU time in ``bench.scale`` did not
    move beyond the load's noise."""
    c = P.blocksize[1]
    indices = np.empty((len(P.indices), c), dtype=P.indices.dtype)
    np.multiply(P.indices[:, None], c, out=indices)
    indices += np.arange(c, dtype=indices.dtype)
    return sp.csr_array((P.data.reshape(-1), indices.reshape(-1), P.indptr * c),
                        shape=P.shape, copy=False)


def galerkin_product(R: sp.spmatrix, A: sp.spmatrix, P: sp.spmatrix,
                     block_values: int = GALERKIN_BLOCK_VALUES) -> sp.bsr_array:
    """The coarse matrix ``R A P``, formed in blocks of its rows.

    ``(R A) P`` whole holds the product ``R A`` (the coarse size times ``A``'s columns, the
    largest matrix of a level's setup); here each block ``R_J`` of about ``block_values``
    stored values of ``R`` gives the rows ``J`` of the answer, ``(R_J A) P`` (pyamg's
    arithmetic, in the same order), written into the answer's arrays, which are sized
    beforehand by the product of the three block patterns (so no block is held twice).

    Args:
        R: (M, N) BSR (or CSR) restriction, blocks (c, b).
        A: (N, N) BSR or CSR matrix, blocks (b, b).
        P: (N, M) BSR (or CSR) prolongator, blocks (b, c).
        block_values: stored values of R per block.

    Returns:
        (M, M) BSR matrix, blocks (c, c); exact zeros dropped as scipy's products drop
        them, each row in the order of scipy's product.

    Example:
        >>> import numpy as np, scipy.sparse as sp
        >>> from pyamg.gallery import poisson
        >>> A = sp.bsr_array(poisson((6,), format="csr"))
        >>> P = sp.bsr_array(np.kron(np.eye(2), np.ones((3, 1))))
        >>> galerkin_product(P.T, A, P, block_values=2).toarray().tolist()
        [[2.0, -1.0], [-1.0, 2.0]]
    """
    R = R if R.format == "bsr" else sp.bsr_array(R)
    P = P if P.format == "bsr" else sp.bsr_array(P)
    rb = R.blocksize[0]
    n_block_rows = R.shape[0] // rb
    runs = [(rows.start, rows.stop)
            for rows, _ in row_runs(R.indptr, block_values // (rb * R.blocksize[1]))]
    # The answer's block pattern, run by run (index arrays only): an upper bound of its
    # stored blocks (the numeric product drops exact zeros).
    A_pattern, P_pattern = block_pattern(A), block_pattern(P)
    bound = sum(int((block_pattern(_block_rows(R, first, last)) @ A_pattern @ P_pattern).nnz)
                for first, last in runs)
    del A_pattern, P_pattern
    dtype = np.result_type(R.dtype, A.dtype, P.dtype)
    index = np.int32 if bound < 2**31 else np.int64
    data = np.empty((bound, rb, rb), dtype=dtype)
    indices = np.empty(bound, dtype=index)
    indptr = np.zeros(n_block_rows + 1, dtype=index)
    at = 0
    for first, last in runs:
        part = sp.bsr_array((_block_rows(R, first, last) @ A) @ P)
        if part.blocksize != (rb, rb):
            part = part.tobsr(blocksize=(rb, rb))
        size = len(part.indices)
        data[at:at + size] = part.data
        indices[at:at + size] = part.indices
        indptr[first + 1:last + 1] = part.indptr[1:] + at
        at += size
        del part
    data.resize((at, rb, rb), refcheck=False)  # in place: scipy's products drop zeros
    indices.resize(at, refcheck=False)
    return sp.bsr_array((data, indices, indptr), shape=(R.shape[0], P.shape[1]),
                        blocksize=(rb, rb), copy=False)


def _block_rows(M: sp.bsr_array, first: int, last: int) -> sp.bsr_array:
    """Block rows ``first:last`` of ``M`` (views of its index and value arrays)."""
    lo, hi = M.indptr[first], M.indptr[last]
    return sp.bsr_array((M.data[lo:hi], M.indices[lo:hi], M.indptr[first:last + 1] - lo),
                        shape=((last - first) * M.blocksize[0], M.shape[1]), copy=False)


def _supported(A: sp.spmatrix, strength: Any, smooth: Any, options: dict[str, Any]) -> bool:
    """Whether :func:`smoothed_aggregation` covers these options (else pyamg's function)."""
    if A.format not in ("csr", "bsr") or A.dtype.kind != "f":
        return False
    if options.get("symmetry", "symmetric") != "symmetric":
        return False
    if options.get("aggregate", "standard") != "standard":
        return False
    if options.get("improve_candidates") is not None:
        return False
    if set(options) - {"symmetry", "aggregate", "improve_candidates", "coarse_solver"}:
        return False
    strengths = strength if isinstance(strength, list) else [strength]
    smoothings = smooth if isinstance(smooth, list) else [smooth]
    if any(_unpack(s)[0] not in SUPPORTED_STRENGTH for s in strengths):
        return False
    for spec in smoothings:
        kind, kwargs = _unpack(spec)
        if kind not in SUPPORTED_SMOOTHING:
            return False
        if kind == "jacobi" and not (set(kwargs) <= {"omega", "weighting", "degree",
                                                      "filter_entries"}
                                     and kwargs.get("weighting", "diagonal") == "local"
                                     and kwargs.get("degree", 1) == 1
                                     and not kwargs.get("filter_entries", False)):
            return False
    return True


def _unpack(spec: Any) -> tuple[Any, dict[str, Any]]:
    return (spec[0], dict(spec[1])) if isinstance(spec, tuple) else (spec, {})


def _blocksize(A: sp.spmatrix) -> int:
    return A.blocksize[0] if A.format == "bsr" else 1
