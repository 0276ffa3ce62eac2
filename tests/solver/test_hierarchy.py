"""Multigrid hierarchies set up in bounded memory (solver.linalg.hierarchy, issue 45).

Independent truth: pyamg's own ``smoothed_aggregation_solver``, ``jacobi_prolongation_smoother``
and ``R @ A @ P`` on the same matrices in the same process: the same levels, the same
prolongator and coarse-matrix patterns and values to the rounding of the matrices'
precision, the same cycle. Families: Eq. 5's matrices of four meshes (closed, with holes,
two components, an open scan) in float32 as the linear solver runs them, the refinement's
Gauss-Newton matrices (scalar and per-vertex), pyamg's Poisson and 2D elasticity (2x3
blocks), both precisions, Jacobi and energy smoothing. Memory: tracemalloc's peak against
pyamg's in the same process.
"""

from __future__ import annotations

import dataclasses
import tracemalloc

import numpy as np
import pyamg
import pytest
import scipy.sparse as sp
from pyamg.aggregation import smooth as pyamg_smooth

from solver.linalg.hierarchy import galerkin_product, smoothed_aggregation
from solver.linalg.prolongation import jacobi_prolongator
from solver.linear.system import near_null_space
from solver.refine.iterative_steps import HIERARCHY_RULES, rigid_modes
from tests.solver.test_eq5_memory import MESHES as EQ5_MESHES
from tests.solver.test_eq5_memory import _problem
from tests.solver.test_prolongation import _gauss_newton_solve, _pieces

JACOBI = {"smooth": ("jacobi", {"weighting": "local"}), "improve_candidates": None,
          "symmetry": "symmetric", "max_coarse": 50, "coarse_solver": "splu"}
ENERGY = {"smooth": ("energy", {"krylov": "cg", "maxiter": 4, "degree": 1,
                                "weighting": "local"}),
          "improve_candidates": None, "symmetry": "symmetric", "max_coarse": 50}


def _gallery(problem: str, size: int, dtype=np.float64) -> tuple[sp.spmatrix, np.ndarray]:
    """pyamg's Poisson (CSR, the constant) or 2D elasticity (BSR 2x2, three rigid modes)
    on a size x size grid, and its near-null space."""
    if problem == "poisson":
        A = pyamg.gallery.poisson((size, size), format="csr")
        B = np.ones((A.shape[0], 1))
    else:
        A, B = pyamg.gallery.linear_elasticity((size, size), format="bsr")
    return A.astype(dtype), B.astype(dtype)


def _relative(theirs: sp.spmatrix, ours: sp.spmatrix) -> float:
    scale = abs(sp.csr_array(theirs)).max()
    return float(abs(sp.csr_array(theirs) - sp.csr_array(ours)).max() / scale)


def _assert_same_hierarchy(theirs, ours, rtol: float) -> None:
    assert [lv.A.shape for lv in ours.levels] == [lv.A.shape for lv in theirs.levels]
    assert len(ours.levels) >= 2
    for mine, reference in zip(ours.levels, theirs.levels, strict=True):
        assert mine.A.nnz == reference.A.nnz
        assert _relative(reference.A, mine.A) <= rtol
        if hasattr(reference, "P"):
            assert mine.P.nnz == reference.P.nnz and mine.R.shape == reference.R.shape
            assert _relative(reference.P, mine.P) <= rtol
    rhs = np.random.default_rng(0).normal(size=theirs.levels[0].A.shape[0])
    rhs = rhs.astype(theirs.levels[0].A.dtype)
    cycled = [ml.aspreconditioner(cycle="V") @ rhs for ml in (theirs, ours)]
    assert np.linalg.norm(cycled[1] - cycled[0]) <= 50 * rtol * np.linalg.norm(cycled[0])


def _pcg_iterations(matrix: sp.spmatrix, ml, tolerance: float) -> int:
    """Iterations of CG on ``matrix`` (float64; ``b = matrix x`` for a random x, so
    consistent where the matrix is singular) preconditioned by one V-cycle of ``ml`` (in
    its own precision)."""
    matrix = sp.csr_array(matrix, dtype=np.float64)
    b = matrix @ np.random.default_rng(2).normal(size=matrix.shape[0])
    cycle = ml.aspreconditioner(cycle="V")
    dtype = ml.levels[0].A.dtype
    x = np.zeros_like(b)
    r = b.copy()
    z = np.asarray(cycle @ r.astype(dtype), dtype=np.float64)
    p, rz = z.copy(), r @ z
    for iteration in range(1, 500):
        Ap = matrix @ p
        alpha = rz / (p @ Ap)
        x += alpha * p
        r -= alpha * Ap
        if np.linalg.norm(r) <= tolerance * np.linalg.norm(b):
            return iteration
        z = np.asarray(cycle @ r.astype(dtype), dtype=np.float64)
        rz, previous = r @ z, rz
        p = z + (rz / previous) * p
    return 500


def _assert_equivalent(theirs, ours, matrix: sp.spmatrix, tolerance: float) -> None:
    """Matrices with cancellations to rounding (Eq. 5's, the Gauss-Newton ones): a block
    that is zero in one precision's order of operations and ~1e-8 in the other's is kept
    by one setup and dropped by the other, so coarser levels may differ in a few
    aggregates. Truth at the preconditioner's level: the same number of levels, sizes
    within 2 %, CG iterations within 10 % (at least 2)."""
    sizes = [[lv.A.shape[0] for lv in ml.levels] for ml in (theirs, ours)]
    assert len(sizes[0]) == len(sizes[1]) >= 2
    assert sizes[0][:2] == sizes[1][:2]  # the finest aggregation is the same
    for theirs_size, ours_size in zip(*sizes, strict=True):
        assert abs(theirs_size - ours_size) <= 0.02 * theirs_size
    assert _relative(theirs.levels[0].P, ours.levels[0].P) <= 1e-5
    counts = [_pcg_iterations(matrix, ml, tolerance) for ml in (theirs, ours)]
    assert counts[0] < 500 and abs(counts[0] - counts[1]) <= max(2, 0.1 * counts[0]), counts


@pytest.mark.parametrize("name", EQ5_MESHES)
def test_eq5_hierarchies_are_pyamgs(name: str):
    """Eq. 5's matrix in float32 with the tree immersion's near-null space, the strength
    graph the matrix itself (as solver.linalg.iterative sets it up)."""
    problem, _, tree = _problem(name)
    K = problem.K.tocsr()
    fine = sp.csr_matrix((K.data.astype(np.float32), K.indices, K.indptr), shape=K.shape)
    B = near_null_space(problem.topology.n_vertices, tree).astype(np.float32)
    options = dict(JACOBI, strength=[("predefined", {"C": fine}), "symmetric"],
                   max_coarse=20)
    theirs = pyamg.smoothed_aggregation_solver(fine, B=B, **options)
    ours = smoothed_aggregation(fine, B=B, **options)
    _assert_equivalent(theirs, ours, K, 1e-8)


@pytest.mark.parametrize("by_vertex", [False, True])
@pytest.mark.parametrize("mesh", ["knight (closed)", "face (open)"])
def test_gauss_newton_hierarchies_are_pyamgs(mesh: str, by_vertex: bool):
    """The refinement's options (energy-minimized prolongators), scalar in float32 and per
    vertex (3x3 blocks) in float64."""
    solve = _gauss_newton_solve(mesh)
    rules = dataclasses.replace(HIERARCHY_RULES, by_vertex=by_vertex,
                                dtype="float64" if by_vertex else "float32")
    A = rules.finest(solve.matrix, solve.positions.shape[1])
    B = rigid_modes(solve.positions).astype(A.dtype)
    options = rules.pyamg_options(A)
    theirs = pyamg.smoothed_aggregation_solver(A, B=B, **options)
    ours = smoothed_aggregation(A, B=B, **options)
    _assert_equivalent(theirs, ours, A, 1e-6)


@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-12), (np.float32, 1e-5)])
@pytest.mark.parametrize("smoothing", ["jacobi", "energy"])
@pytest.mark.parametrize("problem", ["poisson", "elasticity"])
def test_gallery_hierarchies_are_pyamgs(problem: str, smoothing: str, dtype, rtol: float):
    A, B = _gallery(problem, 90 if problem == "poisson" else 50, dtype)
    options = JACOBI if smoothing == "jacobi" else ENERGY
    theirs = pyamg.smoothed_aggregation_solver(A, B=B, **options)
    ours = smoothed_aggregation(A, B=B, **options)
    _assert_same_hierarchy(theirs, ours, rtol)


@pytest.mark.parametrize("options", [
    {"aggregate": "naive"},
    {"smooth": ("jacobi", {"weighting": "diagonal"})},
    {"smooth": ("richardson", {})},
    {"strength": "classical"},
    {"symmetry": "hermitian"},
    {"improve_candidates": ("gauss_seidel", {})},
    {"keep": True},
], ids=lambda options: next(iter(options)))
def test_options_it_does_not_cover_go_to_pyamg(options, monkeypatch):
    """pyamg's function gets the whole call, unchanged; covered options never reach it."""
    A = pyamg.gallery.poisson((40, 40), format="csr")
    B = np.ones((A.shape[0], 1))
    calls = []
    original = pyamg.smoothed_aggregation_solver

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return original(*args, **kwargs)

    monkeypatch.setattr(pyamg, "smoothed_aggregation_solver", spy)
    options = {"max_coarse": 20, "improve_candidates": None, **options}
    ml = smoothed_aggregation(A, B=B, **options)
    assert len(calls) == 1 and all(calls[0][key] == value for key, value in options.items())
    assert len(ml.levels) >= 2
    smoothed_aggregation(A, B=B, **JACOBI)
    assert len(calls) == 1


@pytest.mark.parametrize("block_values", [1, 7, 1000, 1 << 22])
@pytest.mark.parametrize("problem", ["poisson", "elasticity"])
def test_galerkin_product_in_blocks_is_r_a_p(problem: str, block_values: int):
    """Any block size, down to one block row at a time; Poisson's constant candidate
    cancels exactly on interior rows (zeros that both drop)."""
    A, B = _gallery(problem, 30 if problem == "poisson" else 20)
    T, _, _ = _pieces(A, B)
    P = jacobi_prolongator(A, T)
    R = P.T
    theirs = sp.bsr_array(R @ A @ P)
    ours = galerkin_product(R, A, P, block_values=block_values)
    assert ours.shape == theirs.shape and ours.blocksize == theirs.blocksize
    assert ours.nnz == theirs.nnz
    np.testing.assert_array_equal(ours.indptr, theirs.indptr)
    np.testing.assert_array_equal(ours.indices, theirs.indices)  # the same order in rows
    np.testing.assert_allclose(ours.data, theirs.data, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("problem", ["poisson", "elasticity"])
def test_jacobi_prolongator_is_pyamgs(problem: str, dtype):
    A, B = _gallery(problem, 50 if problem == "poisson" else 30, dtype)
    T, C, B_coarse = _pieces(A, B)
    for omega in (4.0 / 3.0, 0.7):
        theirs = sp.bsr_array(pyamg_smooth.jacobi_prolongation_smoother(
            A, T, C, B_coarse, omega=omega, weighting="local"))
        ours = jacobi_prolongator(A, T, omega=omega)
        assert ours.nnz == theirs.nnz and ours.blocksize == theirs.blocksize
        assert _relative(theirs, ours) <= (1e-12 if dtype == np.float64 else 1e-6)


def test_setup_memory_is_a_fraction_of_pyamgs():
    """tracemalloc's peak of a whole Jacobi hierarchy setup above what was live, in the same
    process (pyamg's: two scaled copies of A, the product, ``R A``)."""
    A, B = pyamg.gallery.linear_elasticity((160, 160), format="bsr")
    A = sp.csr_array(A).astype(np.float32)
    B = B.astype(np.float32)

    def peak(setup):
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        ml = setup(A, B=B, **JACOBI)
        used = tracemalloc.get_traced_memory()[1] - before
        tracemalloc.stop()
        return used, ml

    theirs, ml_theirs = peak(pyamg.smoothed_aggregation_solver)
    ours, ml_ours = peak(smoothed_aggregation)
    _assert_same_hierarchy(ml_theirs, ml_ours, 1e-5)
    assert ours < 0.8 * theirs, (ours, theirs)
