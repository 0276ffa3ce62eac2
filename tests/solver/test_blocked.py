"""Blocked in-place array updates (solver.linalg.blocked) and the one CG loop
(solver.linalg.iterative.conjugate_gradients), against numpy, scipy and the direct solve."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver.linalg.blocked import (
    axpy,
    block_pattern,
    leading_blocks,
    row_runs,
    run_block_rows,
    shrunk,
)
from solver.linalg.iterative import conjugate_gradients


@pytest.mark.parametrize("shape", [(0,), (1,), (1000,), (37, 3, 3), (500, 1, 4)])
@pytest.mark.parametrize("values_per_block", [1, 7, 64, 1 << 20])
def test_axpy_adds_in_blocks_what_numpy_adds_at_once(shape: tuple[int, ...],
                                                     values_per_block: int) -> None:
    rng = np.random.default_rng(len(shape) * 100 + values_per_block)
    y, x = rng.normal(size=shape), rng.normal(size=shape)
    expected = y + 0.37 * x
    axpy(y, x, 0.37, values_per_block)
    np.testing.assert_array_equal(y, expected)  # elementwise: the same rounding


def test_axpy_updates_a_strided_column_and_keeps_single_precision() -> None:
    rng = np.random.default_rng(1)
    table, x = rng.normal(size=(1000, 3)), rng.normal(size=1000)
    expected = table.copy()
    expected[:, 1] += -2.5 * x
    axpy(table[:, 1], x, -2.5, values_per_block=100)
    np.testing.assert_array_equal(table, expected)
    y32, x32 = np.ones(10, np.float32), np.full(10, 3.0, np.float32)
    axpy(y32, x32, 1.0 / 3.0, values_per_block=4)
    assert y32.dtype == np.float32
    np.testing.assert_array_equal(y32, np.float32(1) + np.float32(1 / 3) * np.float32(3))


@pytest.mark.parametrize("values_per_block", [1, 5, 9, 100])
def test_leading_blocks_cover_the_rows_once_in_order(values_per_block: int) -> None:
    array = np.zeros((23, 2, 2))
    parts = list(leading_blocks(array, values_per_block))
    covered = np.concatenate([np.arange(23)[p] for p in parts])
    np.testing.assert_array_equal(covered, np.arange(23))
    assert all(len(np.arange(23)[p]) >= 1 for p in parts)
    assert max(len(np.arange(23)[p]) for p in parts) == min(23, max(1, values_per_block // 4))


def _random_csr(rows: int, columns: int, density: float, seed: int) -> sp.csr_array:
    matrix = sp.random_array((rows, columns), density=density, format="csr",
                             rng=np.random.default_rng(seed))
    matrix.sort_indices()
    return matrix


@pytest.mark.parametrize("blocks_per_run", [1, 3, 17, 10_000])
@pytest.mark.parametrize("seed", [0, 1])
def test_row_runs_split_whole_rows_and_their_entries(blocks_per_run: int, seed: int) -> None:
    matrix = _random_csr(200, 50, 0.05, seed)
    matrix.indptr[50:60] = matrix.indptr[50]  # a stretch of empty rows
    indptr = np.asarray(matrix.indptr)
    runs = list(row_runs(indptr, blocks_per_run))
    assert runs[0][0].start == 0 and runs[-1][0].stop == 200
    for (rows, _), (next_rows, _) in itertools.pairwise(runs):
        assert rows.stop == next_rows.start
    for rows, entries in runs:
        assert (entries.start, entries.stop) == (indptr[rows.start], indptr[rows.stop])
        if rows.stop - rows.start > 1:  # only a single row may exceed the run size
            assert entries.stop - entries.start <= blocks_per_run + np.diff(indptr).max()
        owners = run_block_rows(indptr, rows)
        expected = np.repeat(np.arange(200), np.diff(indptr))[entries]
        np.testing.assert_array_equal(owners, expected)


def test_block_pattern_is_the_stored_blocks() -> None:
    csr = _random_csr(30, 12, 0.2, 3)
    np.testing.assert_array_equal(block_pattern(csr).toarray(), csr.toarray() != 0)
    bsr = sp.bsr_array(np.kron(csr.toarray(), np.ones((3, 2))), blocksize=(3, 2))
    pattern = block_pattern(bsr)
    assert pattern.shape == (30, 12) and pattern.dtype == bool
    np.testing.assert_array_equal(pattern.toarray(), csr.toarray() != 0)


def test_shrunk_resizes_its_own_array_and_copies_a_view() -> None:
    own = np.empty((6, 2))  # its own memory (a reshape would be a view)
    own[:] = np.arange(12.0).reshape(6, 2)
    small = shrunk(own, 4)
    assert small is own and small.shape == (4, 2) and small.flags.owndata
    np.testing.assert_array_equal(small, np.arange(8.0).reshape(4, 2))
    parent = np.arange(10.0)
    view = parent[2:]
    copy = shrunk(view, 3)
    np.testing.assert_array_equal(copy, [2.0, 3.0, 4.0])
    assert not np.shares_memory(copy, parent) and len(parent) == 10


def _spd(n: int, seed: int) -> sp.csr_array:
    """A sparse SPD matrix: a mesh-like graph Laplacian plus a small shift."""
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, 6 * n)
    j = rng.integers(0, n, 6 * n)
    keep = i != j
    W = sp.coo_array((rng.uniform(0.5, 2.0, keep.sum()), (i[keep], j[keep])), shape=(n, n))
    W = (W + W.T).tocsr()
    L = sp.diags_array(np.asarray(W.sum(axis=1)).ravel()) - W
    return (L + 1e-2 * sp.eye_array(n)).tocsr()


def _jacobi(K: sp.csr_array):
    inverse = 1.0 / K.diagonal()

    def precondition(r: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        if out is None:
            return r * inverse
        np.multiply(r, inverse, out=out)
        return out

    return precondition


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_conjugate_gradients_reaches_the_direct_answer(seed: int) -> None:
    K = _spd(400, seed)
    b = np.random.default_rng(seed + 10).normal(size=400)
    x = np.zeros(400)
    iterations, residual = conjugate_gradients(K.__matmul__, _jacobi(K), x, b.copy(),
                                               1e-10 * np.linalg.norm(b), 2000)
    exact = spla.spsolve(K.tocsc(), b)
    assert 0 < iterations < 2000
    assert residual <= 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(np.linalg.norm(K @ x - b), residual, rtol=1e-3, atol=1e-12)
    assert np.linalg.norm(x - exact) <= 1e-6 * np.linalg.norm(exact)


def test_conjugate_gradients_from_a_guess_in_a_strided_column() -> None:
    K = _spd(300, 4)
    b = np.random.default_rng(5).normal(size=300)
    exact = spla.spsolve(K.tocsc(), b)
    table = np.zeros((300, 3))
    table[:, 2] = exact + 1e-3 * np.random.default_rng(6).normal(size=300)
    column = table[:, 2]
    r = b - K @ column
    target = 1e-9 * np.linalg.norm(b)
    from_guess, _ = conjugate_gradients(K.__matmul__, _jacobi(K), column, r, target, 2000)
    from_zero, _ = conjugate_gradients(K.__matmul__, _jacobi(K), np.zeros(300), b.copy(),
                                       target, 2000)
    assert np.linalg.norm(table[:, 2] - exact) <= 1e-7 * np.linalg.norm(exact)
    assert not table[:, :2].any()
    assert from_guess < from_zero


def test_conjugate_gradients_stops_at_the_cap_and_at_once_when_done() -> None:
    K = _spd(300, 7)
    b = np.random.default_rng(8).normal(size=300)
    x = np.zeros(300)
    iterations, residual = conjugate_gradients(K.__matmul__, _jacobi(K), x, b.copy(),
                                               0.0, 5)
    assert iterations == 5 and residual > 0
    np.testing.assert_allclose(np.linalg.norm(b - K @ x), residual, rtol=1e-8)
    x = np.zeros(300)
    assert conjugate_gradients(K.__matmul__, _jacobi(K), x, np.zeros(300), 0.0, 50) == (0, 0.0)
    assert not x.any()


def test_conjugate_gradients_stops_on_a_direction_without_curvature() -> None:
    K = sp.diags_array([1.0, 1.0, -1.0]).tocsr()  # indefinite: p.K p = 0 for p = (1, 0, 1)
    x = np.zeros(3)
    iterations, residual = conjugate_gradients(
        K.__matmul__, lambda r, out: r.copy(), x, np.array([1.0, 0.0, 1.0]), 1e-12, 10)
    assert iterations == 0 and residual == pytest.approx(np.sqrt(2.0))
    assert not x.any()


def test_conjugate_gradients_with_a_single_precision_preconditioner() -> None:
    """CG reaches a float64 tolerance where the preconditioner is applied in float32 (as
    the multigrid cycles are), symmetric only to its rounding."""
    K = _spd(500, 9)
    inverse = (1.0 / K.diagonal()).astype(np.float32)

    def rounded(r: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        return (r.astype(np.float32) * inverse).astype(np.float64)

    b = np.random.default_rng(11).normal(size=500)
    x = np.zeros(500)
    iterations, residual = conjugate_gradients(K.__matmul__, rounded, x, b.copy(),
                                               1e-9 * np.linalg.norm(b), 3000)
    assert residual <= 1e-9 * np.linalg.norm(b) and iterations < 3000
    assert np.linalg.norm(K @ x - b) <= 2e-9 * np.linalg.norm(b)
