"""Arrays updated in blocks: in-place arithmetic on large vectors and sparse values without a
temporary of their full size.

A numpy expression such as ``y += alpha * x`` makes ``alpha * x`` whole before adding it: at
1.6M faces one (N,) column of Eq. 5 is 45 MB and a prolongator's values hundreds of MB. The
helpers here run such updates over leading blocks (:func:`leading_blocks`, :func:`axpy`) or
over runs of whole block rows of a CSR/BSR matrix (:func:`row_runs`), so the temporaries stay
a few MB. They serve CG's vector updates (:mod:`solver.linalg.iterative`), the in-place
prolongators (:mod:`solver.linalg.prolongation`) and the blocked coarse products
(:mod:`solver.linalg.hierarchy`).

Example:
    >>> import numpy as np
    >>> y, x = np.ones(5), np.arange(5.0)
    >>> axpy(y, x, 2.0, values_per_block=2)
    >>> y.tolist()
    [1.0, 3.0, 5.0, 7.0, 9.0]
    >>> [(r.start, r.stop, e.start, e.stop) for r, e in row_runs(np.array([0, 2, 4, 5]), 3)]
    [(0, 1, 0, 2), (1, 3, 2, 5)]
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import numpy as np
import scipy.sparse as sp

BLOCK_VALUES = 1 << 20
"""Values per block of the in-place updates of a prolongator's values: their temporaries
stay a few MB."""
RUN_VALUES = 1 << 17
"""Stored values per run of whole block rows (row sums, row scaling, the tentative
prolongator's blocks, dropping zero blocks): each run's temporaries (int64 positions,
double-precision sums) stay ~1 MB."""
ROWS_PER_UPDATE = 1 << 16
"""Rows of CG's vector updates at once: ``x += alpha p`` and ``r -= alpha K p`` in contiguous
row blocks (512 KB each in float64, within a core's cache), so that no (N,) temporary is
made (45 MB at 1.6M faces)."""


def leading_blocks(array: np.ndarray, values_per_block: int = BLOCK_VALUES,
                   ) -> Iterator[slice]:
    """Slices of ``array``'s first axis holding about ``values_per_block`` values each (at
    least one row per slice)."""
    row_size = array[0].size if len(array) and array.ndim > 1 else 1
    step = max(1, int(values_per_block) // max(1, row_size))
    for lo in range(0, len(array), step):
        yield slice(lo, lo + step)


def axpy(y: np.ndarray, x: np.ndarray, alpha: float,
         values_per_block: int = BLOCK_VALUES) -> None:
    """``y += alpha x`` in place (``y``, ``x`` of one shape, ``y`` may be a strided view),
    block by block along the first axis; ``alpha`` is taken in ``y``'s precision."""
    alpha = y.dtype.type(alpha)
    for part in leading_blocks(y, values_per_block):
        y[part] += alpha * x[part]


def block_pattern(M: sp.spmatrix) -> sp.csr_array:
    """Boolean CSR of the stored blocks of a CSR or BSR ``M`` (its own index arrays, one
    byte per block; a product of two keeps every structural entry)."""
    rb, cb = M.blocksize if M.format == "bsr" else (1, 1)
    return sp.csr_array((np.ones(len(M.indices), dtype=bool), M.indices, M.indptr),
                        shape=(M.shape[0] // rb, M.shape[1] // cb))


def row_runs(indptr: np.ndarray, blocks_per_run: int = RUN_VALUES // 4,
             ) -> Iterator[tuple[slice, slice]]:
    """Runs of whole block rows of a CSR/BSR ``indptr`` with about ``blocks_per_run`` stored
    blocks each (a longer row is a run of its own; empty rows may form runs with no
    entries): (block rows, their entries)."""
    step = max(1, int(blocks_per_run))
    cuts = np.searchsorted(indptr, np.arange(0, indptr[-1], step), side="right") - 1
    bounds = np.unique(np.append(cuts, [0, len(indptr) - 1]))
    for first, last in itertools.pairwise(bounds.tolist()):
        yield slice(first, last), slice(int(indptr[first]), int(indptr[last]))


def run_block_rows(indptr: np.ndarray, rows: slice) -> np.ndarray:
    """The block row of each entry of the run ``rows`` of a CSR/BSR ``indptr`` (int64)."""
    return np.repeat(np.arange(rows.start, rows.stop, dtype=np.int64),
                     np.diff(indptr[rows.start:rows.stop + 1]))


def shrunk(array: np.ndarray, length: int) -> np.ndarray:
    """The first ``length`` rows of ``array``: shrunk in place where it owns its memory, a
    copy where it is a view."""
    if array.base is None and array.flags.owndata:
        array.resize((length, *array.shape[1:]), refcheck=False)
        return array
    return array[:length].copy()
