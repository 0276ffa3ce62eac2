"""Eq. 5's memory on the iterative path (issue 45): a handed-over K is constrained in place,
the released rows leave the energies unchanged, and the multigrid's fine strength graph is
the matrix itself. Truths: the copying construction, the rows' energies and pyamg's own
strength of connection."""

from __future__ import annotations

import numpy as np
import pyamg
import pytest
import scipy.sparse as sp

from solver.immersion import ImmersionProblem
from solver.linear.system import ConstrainedSystem, near_null_space
from solver.mesh.forms import validate_forms
from tests.solver.test_iterative import _forms, _relative

MESHES = ["icosphere", "holes", "two-parts", "face.off"]


def _problem(name: str, noise: float = 1e-2, isolated: int = 0):
    forms, angles, n = _forms(name, noise)
    topology, L, A = validate_forms(forms.faces, forms.edges, forms.lengths, angles,
                                    n + isolated)
    problem = ImmersionProblem(topology, L, A)
    anchor, roots = problem.anchors(np.ones(topology.n_components, dtype=bool))
    tree = problem.tree_unknowns([r["face"] for r in roots], [r["vertex"] for r in roots])
    return problem, anchor, tree


@pytest.mark.parametrize("name", MESHES)
@pytest.mark.parametrize("isolated", [0, 2])
@pytest.mark.parametrize("method", ["direct", "iterative"])
def test_a_handed_over_k_is_constrained_in_place(name: str, isolated: int, method: str):
    """The system built from a handed-over K (arrays reused where every diagonal entry is
    stored; unused vertices have none: the copying fallback) solves as one built from a
    copy of K, with soft constraints on some unknowns."""
    problem, anchor, tree = _problem(name, isolated=isolated)
    rng = np.random.default_rng(1)
    soft = rng.choice(problem.topology.n_vertices - isolated, 5, replace=False)
    weights, values = rng.uniform(0.5, 2.0, 5), rng.normal(size=(5, 3))
    near_null = near_null_space(problem.topology.n_vertices, tree)
    common = dict(method=method, near_null=near_null)
    copied = ConstrainedSystem(problem.K.copy(), anchor.hard_columns, soft, weights,
                               **common)
    K = problem.K
    data = K.data
    handed = ConstrainedSystem(lambda: problem.__dict__.pop("K"), anchor.hard_columns,
                               soft, weights, **common)
    del K
    if method == "iterative":
        reused = np.shares_memory(handed.iterative.matrix.data, data)
        assert reused == (isolated == 0)
    truth = copied.solve(anchor.hard_values, values, tree)
    u = handed.solve(anchor.hard_values, values, tree)
    assert _relative(u, truth) < (1e-9 if method == "direct" else 1e-6)


@pytest.mark.parametrize("name", MESHES)
def test_energies_after_release_are_those_of_the_rows(name: str):
    problem, anchor, _ = _problem(name)
    u = problem.system(anchor).solve(anchor.hard_values, np.zeros((0, 3)))
    rows = problem.energies(u)
    problem.release_linear()
    assert "_rows" not in problem.__dict__ and "K" not in problem.__dict__
    released = problem.energies(u)
    for key in ("edge", "frame"):
        assert released[key] == pytest.approx(rows[key], rel=1e-10, abs=1e-14)
    problem.system(anchor, release=True)  # the last system drops the rows as well
    assert "_rows" not in problem.__dict__


@pytest.mark.parametrize("name", MESHES)
def test_the_fine_strength_graph_gives_pyamgs_own_prolongator(name: str):
    """The fine level's strength graph given as the matrix itself: the same aggregates,
    hence the same prolongators (to float32 rounding) and levels as pyamg's symmetric
    strength (theta 0)."""
    problem, anchor, tree = _problem(name)
    system = problem.system(anchor, method="iterative",
                            near_null=near_null_space(problem.topology.n_vertices, tree))
    ours = system.iterative._ml
    fine = ours.levels[0].A
    candidates = near_null_space(problem.topology.n_vertices, tree).astype(fine.dtype)
    candidates[system.hard_columns] = 0.0  # as the system gives them to its solver
    reference = pyamg.smoothed_aggregation_solver(
        fine, B=candidates, max_coarse=500, coarse_solver="splu",
        smooth=("jacobi", {"weighting": "local"}), improve_candidates=None)
    assert len(ours.levels) == len(reference.levels) >= 2
    for mine, theirs in zip(ours.levels[:-1], reference.levels[:-1], strict=True):
        assert mine.P.shape == theirs.P.shape and mine.P.nnz == theirs.P.nnz
        # float32: pyamg scales A before the product, solver.linalg.hierarchy after it
        difference = abs(sp.csr_matrix(mine.P) - sp.csr_matrix(theirs.P)).max()
        assert difference <= 1e-5 * abs(theirs.P).max()
