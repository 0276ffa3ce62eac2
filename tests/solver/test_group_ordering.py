"""The ``groups`` ordering hint of :func:`solver.linalg.factorize` (compressed-graph ordering).

Checks against independent truth: solutions are compared with a dense solve of the same
matrix, and the ordering's effect is read from PARDISO's own fill count.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from solver import fundamental_forms, linalg
from solver.immersion import ImmersionProblem
from solver.linear.system import unknown_groups
from solver.mesh.topology import build_topology

pytestmark = pytest.mark.skipif("pardiso" not in linalg.available_backends(),
                                reason="PARDISO not installed")


def _system() -> tuple[sp.csr_array, np.ndarray]:
    """The anchored reconstruction matrix of a noisy icosphere and its unknown groups."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    forms = fundamental_forms(mesh.vertices, mesh.faces)
    angles = forms.angles + np.random.default_rng(3).normal(scale=1e-3, size=len(forms.angles))
    topo = build_topology(forms.faces, n_vertices=len(mesh.vertices))
    problem = ImmersionProblem(topo, forms.lengths, angles)
    anchor, _ = problem.anchors(np.ones(topo.n_components, dtype=bool))
    system = problem.system(anchor, "superlu")
    return sp.csr_array(system.factor._matrix), unknown_groups(topo.n_vertices, topo.n_faces)


def test_grouped_ordering_solves_like_a_dense_solve_and_keeps_unknowns_of_a_group_together():
    K, groups = _system()
    rhs = np.random.default_rng(0).normal(size=(K.shape[0], 3))
    expected = np.linalg.solve(K.toarray(), rhs)
    linalg.clear_analysis_cache()
    fact = linalg.factorize(K, "pardiso", assume_symmetric=True, groups=groups)
    assert fact.analysis == "computed"
    x = fact.solve(rhs)
    assert np.abs(x - expected).max() <= 1e-9 * np.abs(expected).max()
    # The ordering PARDISO used lists each face's three frame unknowns consecutively.
    perm = fact._solver._handle.perm
    n_vertices = int(np.flatnonzero(np.diff(groups) == 0)[0])  # first frame unknown
    frame = perm[perm >= n_vertices]
    starts = frame[::3]
    assert np.array_equal(frame[1::3], starts + 1) and np.array_equal(frame[2::3], starts + 2)
    assert sorted(perm.tolist()) == list(range(K.shape[0]))


def test_grouped_and_plain_orderings_agree_and_the_cache_serves_both():
    K, groups = _system()
    rhs = np.random.default_rng(1).normal(size=(K.shape[0], 3))
    linalg.clear_analysis_cache()
    plain = linalg.factorize(K, "pardiso", assume_symmetric=True)
    fill_plain = int(plain._solver._handle.iparm[17])
    x_plain = plain.solve(rhs)
    linalg.clear_analysis_cache()
    grouped = linalg.factorize(K, "pardiso", assume_symmetric=True, groups=groups)
    fill_grouped = int(grouped._solver._handle.iparm[17])
    x_grouped = grouped.solve(rhs)
    assert np.abs(x_grouped - x_plain).max() <= 1e-12 * np.abs(x_plain).max()
    # Nested dissection of the compressed graph: no more than 25% more fill than the full.
    assert fill_grouped <= 1.25 * fill_plain
    again = linalg.factorize(K, "pardiso", assume_symmetric=True, groups=groups)
    assert again.analysis == "cached"
    assert np.abs(again.solve(rhs) - x_grouped).max() <= 1e-12 * np.abs(x_grouped).max()


def test_any_grouping_gives_the_same_solution():
    """The hint only changes the ordering: a random grouping still solves exactly."""
    K, _ = _system()
    rhs = np.random.default_rng(2).normal(size=K.shape[0])
    expected = np.linalg.solve(K.toarray(), rhs)
    random_groups = np.random.default_rng(4).integers(0, K.shape[0] // 2, size=K.shape[0])
    linalg.clear_analysis_cache()
    x = linalg.factorize(K, "pardiso", assume_symmetric=True, groups=random_groups).solve(rhs)
    assert np.abs(x - expected).max() <= 1e-9 * np.abs(expected).max()


@pytest.mark.parametrize("kind", ["short", "strings", "negative", "float", "too_large"])
def test_bad_groups_are_refused(kind: str):
    K, groups = _system()
    bad = {"short": groups[:3], "strings": np.array(["a"] * K.shape[0]),
           "negative": groups - 1, "float": groups.astype(np.float64),
           "too_large": groups + K.shape[0]}[kind]
    with pytest.raises(ValueError, match="groups"):
        linalg.factorize(K, "pardiso", assume_symmetric=True, groups=bad)
