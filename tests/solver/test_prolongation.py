"""Energy-minimizing prolongators computed in place (solver.linalg.prolongation, issue 45).

Independent truth: pyamg's own ``energy_prolongation_smoother`` on the same matrices, in the
same process: the same pattern and the same values to the rounding of the matrices'
precision (the in-place version sums the Frobenius inner products in double precision), and
whole hierarchies with the same levels and CG iterations. Families: the refinement's
Gauss-Newton matrices of four meshes (closed genus 0 and 1, open; scalar float32 and
per-vertex float64 hierarchies), pyamg's 2D elasticity (2x2 blocks) and Poisson problems,
both weightings. Its memory is measured against pyamg's by tracemalloc in the same process.
"""

import dataclasses
import tracemalloc

import numpy as np
import pyamg
import pytest
import scipy.sparse as sp
from pyamg.aggregation import smooth as pyamg_smooth

from solver import fundamental_forms, reconstruct
from solver.linalg.prolongation import energy_prolongator
from solver.refine.iterative_steps import (
    HIERARCHY_RULES,
    Multigrid,
    observe_solves,
    rigid_modes,
)
from solver.refine.steps import DEFAULT_STEP_RULES
from tests.helpers.meshes import load, sphere_cap, with_noisy_angles

MESHES = {
    "knight (closed)": lambda: load("decimated-knight.off"),
    "torus (genus 1)": lambda: load("torus.off"),
    "face (open)": lambda: load("face.off"),
    "sphere cap (open)": sphere_cap,
}


def _gauss_newton_solve(name):
    """The first Gauss-Newton solve of ``name``'s noisy forms by the iterative path."""
    V, F = MESHES[name]()
    forms = with_noisy_angles(fundamental_forms(V, F))
    seen = []
    with observe_solves(seen.append):
        reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                    n_vertices=len(V), linear_solver="iterative")
    assert seen, "the refinement solved nothing"
    return seen[0]


def _pieces(A, B):
    """pyamg's first level before smoothing: strength, aggregates, tentative prolongator."""
    C = pyamg.strength.symmetric_strength_of_connection(A, 0.0)
    aggregates, _ = pyamg.aggregation.standard_aggregation(C)
    T, B_coarse = pyamg.aggregation.fit_candidates(aggregates, B)
    return T, C, B_coarse


def _both(A, B, **options):
    T, C, B_coarse = _pieces(A, B)
    theirs = pyamg_smooth.energy_prolongation_smoother(
        A, T.copy(), C, B_coarse, B, (False, {}), **options)
    ours = energy_prolongator(A, T.copy(), C, B_coarse, B, (False, {}), **options)
    return sp.bsr_array(theirs), sp.bsr_array(ours)


def _assert_same(theirs, ours, rtol):
    theirs.sort_indices()
    ours.sort_indices()
    assert theirs.blocksize == ours.blocksize and theirs.shape == ours.shape
    np.testing.assert_array_equal(ours.indptr, theirs.indptr)
    np.testing.assert_array_equal(ours.indices, theirs.indices)
    scale = np.abs(theirs.data).max()
    assert np.abs(ours.data.astype(float) - theirs.data).max() <= rtol * scale


@pytest.mark.parametrize("name", sorted(MESHES))
@pytest.mark.parametrize("dtype, rtol", [("float32", 2e-5), ("float64", 1e-11)])
def test_gauss_newton_prolongators_are_pyamgs(name, dtype, rtol):
    solve = _gauss_newton_solve(name)
    rules = dataclasses.replace(HIERARCHY_RULES, dtype=dtype)
    A = rules.finest(solve.matrix, solve.positions.shape[1])
    B = rigid_modes(solve.positions).astype(A.dtype)
    theirs, ours = _both(A, B, maxiter=8)
    _assert_same(theirs, ours, rtol)
    assert ours.dtype == A.dtype


@pytest.mark.parametrize("weighting", ["local", "diagonal"])
@pytest.mark.parametrize("maxiter", [1, 4])
def test_block_elasticity_and_weightings(weighting, maxiter):
    A, B = pyamg.gallery.linear_elasticity((24, 24), format="bsr")
    theirs, ours = _both(A, B, maxiter=maxiter, weighting=weighting)
    assert ours.blocksize == (2, 3)
    _assert_same(theirs, ours, 1e-10)


def test_poisson_with_degree_two():
    A = pyamg.gallery.poisson((40, 40), format="csr")
    theirs, ours = _both(A, np.ones((A.shape[0], 1)), maxiter=4, degree=2)
    _assert_same(theirs, ours, 1e-10)


def test_options_it_does_not_cover_go_to_pyamg():
    A = pyamg.gallery.poisson((30, 30), format="csr")
    theirs, ours = _both(A, np.ones((A.shape[0], 1)), maxiter=3, krylov="gmres")
    _assert_same(theirs, ours, 0.0)
    theirs, ours = _both(A, np.ones((A.shape[0], 1)), maxiter=3, weighting="block")
    _assert_same(theirs, ours, 0.0)


def test_whole_hierarchy_same_levels_and_iterations():
    """The refinement's Multigrid set up by pyamg (its own strength graph) and by
    solver.linalg.hierarchy (the matrix as strength graph): the same levels and the same CG
    iterations on a Gauss-Newton solve."""
    solve = _gauss_newton_solve("knight (closed)")
    counts = {}
    for label, rules in {
            "pyamg": dataclasses.replace(HIERARCHY_RULES, bounded_setup=False,
                                         strength_is_matrix=False),
            "in place": HIERARCHY_RULES}.items():
        multigrid = Multigrid(300, DEFAULT_STEP_RULES.cg_resetup_growth,
                              DEFAULT_STEP_RULES.cg_setup_iterations, rules)
        operator = multigrid.operator(solve.matrix, solve.positions, solve.project)
        operator.tolerance = 1e-6
        operator.solve(solve.rhs)
        levels = [level.A.shape for level in multigrid._ml.levels]
        counts[label] = (levels, multigrid.stats.iterations[-1])
    assert counts["in place"][0] == counts["pyamg"][0]
    assert abs(counts["in place"][1] - counts["pyamg"][1]) <= 1


def test_memory_is_a_fraction_of_pyamgs():
    """The transient of one smoothing (tracemalloc's peak above what is live), in the same
    process: pyamg's keeps ~10 matrices of the pattern's size, this one four value arrays."""
    A, B = pyamg.gallery.linear_elasticity((160, 160), format="bsr")
    T, C, B_coarse = _pieces(A, B)

    def transient(function):
        arguments = (A, T.copy(), C, B_coarse, B, (False, {}))
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        P = function(*arguments, maxiter=8)
        peak = tracemalloc.get_traced_memory()[1] - before
        tracemalloc.stop()
        return peak, P

    theirs, P_theirs = transient(pyamg_smooth.energy_prolongation_smoother)
    ours, P_ours = transient(energy_prolongator)
    _assert_same(sp.bsr_array(P_theirs), P_ours, 1e-10)
    assert ours < 0.6 * theirs, (ours, theirs)
