"""solver.refine.mixed_precision: a float32 factor whose solves are refined in float64."""

import numpy as np
import pytest
import scipy.sparse as sp

from solver import linalg
from solver.refine.mixed_precision import ImpreciseSolveError, SinglePrecisionFactor

pytestmark = pytest.mark.skipif("pardiso" not in linalg.available_backends(),
                                reason="single precision needs PARDISO")


def spd_upper(n: int = 400, seed: int = 0) -> tuple[sp.csr_array, sp.csr_array]:
    """A sparse SPD matrix (a 1D Laplacian plus a random diagonal, condition ~1e4) and its
    upper triangle as the factor reads it."""
    rng = np.random.default_rng(seed)
    K = sp.diags_array([-np.ones(n - 1), 2.0 + rng.uniform(1e-4, 1e-3, n), -np.ones(n - 1)],
                       offsets=[-1, 0, 1], format="csr")
    upper = sp.csr_array(sp.triu(K, format="csr"))
    upper.sort_indices()
    return K, upper


def test_one_refinement_step_gives_double_precision_accuracy_to_float32_factor():
    """The refined answer agrees with the double-precision solution far beyond float32's
    accuracy (a float32 solve alone is off by ~1e-7 x the condition number)."""
    K, upper = spd_upper()
    factor = SinglePrecisionFactor(upper)
    assert factor.precision == "single"
    b = np.random.default_rng(1).normal(size=K.shape[0])
    exact = sp.linalg.spsolve(sp.csc_array(K), b)
    alone = factor._factor.solve(b)
    refined = factor.solve(b)
    error = np.abs(refined - exact).max() / np.abs(exact).max()
    assert np.abs(alone - exact).max() / np.abs(exact).max() > 1e-7
    assert error < 1e-3 * np.abs(alone - exact).max() / np.abs(exact).max()


def test_an_inexact_or_overflowing_single_precision_solve_is_refused():
    """A correction above the tolerance, or a right-hand side float32 cannot hold, raises
    ImpreciseSolveError (the refinement then factorizes in double)."""
    K, upper = spd_upper()
    b = np.ones(K.shape[0])
    with pytest.raises(ImpreciseSolveError):
        SinglePrecisionFactor(upper, tolerance=0.0).solve(b)
    with pytest.raises(ImpreciseSolveError):
        SinglePrecisionFactor(upper).solve(1e39 * b)
