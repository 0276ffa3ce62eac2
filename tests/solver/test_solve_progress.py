"""Progress within long iterative solves (issue 45: a 5M-face answer spends tens of minutes
in Eq. 5's CG and in each Gauss-Newton step): ``progress(stage, fraction)`` moves while CG
iterates, never goes back, and observing does not change the answer.

Independent truth: the same solve without an observer (answers equal to the bit), CG's own
residuals (the fraction is the share of the digits taken off, recomputed here from the
residual history CG reports), the refinement's own iteration count, and scipy's direct
solve for the linear system the fractions follow.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver import fundamental_forms, reconstruct
from solver.linalg.iterative import (
    IterativeSolver,
    SolveProgress,
    conjugate_gradients,
    digits_share,
)
from tests.helpers.meshes import double_torus, load, with_noisy_angles


def _poisson(n: int) -> sp.csr_matrix:
    """The 2-D five-point Laplacian of an n x n grid plus a small shift (SPD)."""
    one = sp.diags_array([[-1.0] * (n - 1), [2.0] * n, [-1.0] * (n - 1)], offsets=[-1, 0, 1])
    eye = sp.identity(n)
    return sp.csr_matrix(sp.kron(one, eye) + sp.kron(eye, one) + 1e-3 * sp.identity(n * n))


def test_digits_share_is_the_share_of_the_decades_taken_off():
    assert digits_share(1.0, 1e-4, 1e-8) == pytest.approx(0.5)
    assert digits_share(10.0, 10.0, 1e-2) == 0.0
    assert digits_share(10.0, 20.0, 1e-2) == 0.0          # a residual that grew
    assert digits_share(10.0, 1e-9, 1e-2) == 1.0          # past the target
    assert digits_share(1e-3, 1e-3, 1e-2) == 1.0          # nothing to do
    assert digits_share(1.0, 0.0, 1e-8) == 1.0            # solved exactly


def test_conjugate_gradients_observes_every_iteration_with_its_residual():
    K = _poisson(20)
    b = np.random.default_rng(1).normal(size=K.shape[0])
    x, r = np.zeros_like(b), b.copy()
    history = []
    iterations, residual = conjugate_gradients(
        K.__matmul__, lambda r, out: r / K.diagonal(), x, r, 1e-8 * np.linalg.norm(b), 1000,
        lambda i, res: history.append((i, res)))
    assert [i for i, _ in history] == list(range(1, iterations + 1))
    assert history[-1][1] == residual
    assert np.linalg.norm(b - K @ x) == pytest.approx(residual, rel=1e-3, abs=1e-12)


@pytest.mark.parametrize("columns", [1, 3])
def test_iterative_solve_reports_a_rising_fraction_and_the_same_answer(columns):
    K = _poisson(60)
    b = np.random.default_rng(columns).normal(size=(K.shape[0], columns))
    quiet = IterativeSolver(K).solve(b)
    seen: list[float] = []
    solver = IterativeSolver(K)
    loud = solver.solve(b, progress=seen.append)
    assert np.array_equal(quiet, loud)
    exact = spla.spsolve(sp.csc_matrix(K), b).reshape(loud.shape)
    assert np.linalg.norm(loud - exact) <= 1e-5 * np.linalg.norm(exact)
    assert seen == sorted(seen) and seen[0] >= 0.0 and seen[-1] == 1.0
    growth = np.diff(seen[:-1])  # the last report may be a smaller step, to 1
    assert (growth >= SolveProgress.step - 1e-12).all()
    assert len(seen) <= 1 + columns * solver.stats.iterations
    # Each column's first report is at its index's share of the whole.
    assert any(abs(f - (columns - 1) / columns) < 0.5 / columns for f in seen)


def test_solve_progress_follows_the_residual_history():
    seen: list[float] = []
    report = SolveProgress(seen.append, columns=2)
    observe = report.column(0)
    for residual in [1.0, 1e-1, 1e-2, 1e-3, 1e-4]:
        observe(1.0, residual, 1e-4)
    observe = report.column(1)
    observe(2.0, 2e-2, 2e-4)
    assert seen == pytest.approx([0.0, 0.125, 0.25, 0.375, 0.5, 0.75])
    assert SolveProgress(None, 3).column(2)(1.0, 0.1, 0.01) is None  # no callback: nothing


def _recorder():
    seen: list[tuple[str, float]] = []
    return seen, lambda stage, fraction: seen.append((stage, fraction))


MESHES = {"knight": lambda: load("decimated-knight.off"), "double torus": double_torus}


@pytest.mark.parametrize("name", MESHES)
def test_reconstruct_reports_progress_within_the_iterative_solve_and_refinement(name):
    V, F = MESHES[name]()
    forms = with_noisy_angles(fundamental_forms(V, F))
    args = (forms.faces, forms.edges, forms.lengths, forms.angles)
    quiet = reconstruct(*args, n_vertices=len(V), linear_solver="iterative")
    seen, progress = _recorder()
    loud = reconstruct(*args, n_vertices=len(V), linear_solver="iterative", progress=progress)
    assert np.array_equal(quiet.vertices, loud.vertices)
    refinement = loud.report["refinement"]
    assert refinement["refined"] and refinement["iterations"] >= 1
    for stage in ("solve", "refine"):
        fractions = [f for s, f in seen if s == stage]
        assert fractions == sorted(fractions), stage
        assert all(0.0 <= f <= 1.0 for f in fractions), stage
        # More reports than the stage's own milestones: CG moves the fraction.
        assert len(set(fractions)) > 3, (stage, fractions)
    refine = [f for s, f in seen if s == "refine" and f < 1.0]
    # Between the accepted steps' fractions (i / (i + 3)) come the solves' own.
    steps = {round(i / (i + 3.0), 12) for i in range(1, refinement["iterations"] + 1)}
    assert len([f for f in refine if round(f, 12) not in steps]) > 0
    assert max(refine) <= 0.99


def test_the_factorizing_refinement_reports_once_per_step():
    V, F = load("decimated-knight.off")
    forms = with_noisy_angles(fundamental_forms(V, F))
    seen, progress = _recorder()
    result = reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                         n_vertices=len(V), linear_solver="direct", progress=progress)
    iterations = result.report["refinement"]["iterations"]
    refine = [f for s, f in seen if s == "refine" and f < 1.0]
    expected = [i / (i + 3.0) for i in range(1, iterations + 1)]
    assert refine[-iterations:] == pytest.approx(expected)
    assert not math.isnan(sum(refine))
