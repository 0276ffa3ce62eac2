"""Tests of the PARDISO analysis cache of solver.linalg (keyed by sparsity pattern)."""

from __future__ import annotations

import gc
import pickle
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.sparse.linalg import spsolve

from solver import Deformer, fundamental_forms, linalg, reconstruct
from solver.immersion import ImmersionProblem
from solver.linalg import SingularSystemError, analysis_cache_info, factorize
from solver.mesh.topology import build_topology

pytestmark = pytest.mark.skipif("pardiso" not in linalg.available_backends(),
                                reason="PARDISO (pypardiso / mkl) not installed")


@pytest.fixture(autouse=True)
def empty_cache() -> Iterator[None]:
    """Every test starts and ends with an empty cache and the default limit."""
    limit = linalg.ANALYSIS_CACHE_BYTES
    gc.collect()
    linalg.clear_analysis_cache()
    yield
    linalg.ANALYSIS_CACHE_BYTES = limit
    gc.collect()
    linalg.clear_analysis_cache()


def grid_mesh(k: int, flip: bool) -> tuple[np.ndarray, np.ndarray]:
    """A k x k vertex grid, a bumpy height field, each quad split along one diagonal
    (``flip`` picks the other one): same vertex and face counts, different connectivity."""
    i, j = np.meshgrid(np.arange(k - 1), np.arange(k - 1), indexing="ij")
    a, b = (i * k + j).ravel(), (i * k + j + 1).ravel()
    c, d = ((i + 1) * k + j).ravel(), ((i + 1) * k + j + 1).ravel()
    if flip:
        faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    else:
        faces = np.concatenate([np.stack([a, d, b], 1), np.stack([a, c, d], 1)])
    x, y = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k), indexing="ij")
    # Jitter: no two triangles alike, so no entry of K cancels to an exact zero.
    x, y = x + np.random.default_rng(k).uniform(-0.2, 0.2, (2, k, k)) / k
    z = 0.1 * np.sin(3 * x) * np.cos(2 * y)
    return np.stack([x.ravel(), y.ravel(), z.ravel()], 1), faces


def noisy_system(vertices: np.ndarray, faces: np.ndarray, seed: int = 0,
                 ) -> tuple[sp.csr_array, np.ndarray]:
    """The anchored reconstruction matrix (explicit zeros where unknowns are eliminated)
    and its right-hand side, for the mesh's forms with noisy dihedral angles."""
    forms = fundamental_forms(vertices, faces)
    inner = forms.angles != 0
    forms.angles[inner] += np.random.default_rng(seed).normal(scale=1e-3, size=inner.sum())
    problem = ImmersionProblem(build_topology(forms.faces, n_vertices=len(vertices)),
                               forms.lengths, forms.angles)
    anchor, _ = problem.anchors(np.ones(problem.topology.n_components, dtype=bool))
    system = problem.system(anchor, "superlu")
    rhs = np.zeros((system.size, 3))
    rhs -= system.K_hard_rows.T @ anchor.hard_values
    rhs[system.hard_columns] = system.hard_diagonal[:, None] * anchor.hard_values
    return sp.csr_array(system.factor._matrix), rhs


def relative(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.abs(x - y).max() / np.abs(y).max())


def hinted(K: sp.csr_array, scale: float = 1.0, **options: object) -> linalg.Factorization:
    """``factorize(scale * K)`` with an ordering hint (one group per unknown): PARDISO is
    then given the ordering, which the cache keeps for a second live factorization."""
    return factorize(scale * K, "pardiso", groups=np.arange(K.shape[0]), **options)


def user_permutation(factor: linalg.Factorization) -> int:
    """The iparm[4] (user permutation mode) of a PARDISO factorization's handle."""
    return int(factor._solver._handle.iparm[4])


def test_miss_then_hit_with_same_pattern_and_new_values() -> None:
    K, b = noisy_system(*grid_mesh(12, False))
    first = hinted(K)
    assert first.analysis == "computed"
    info = analysis_cache_info()
    assert (info["patterns"], info["computed"], info["cached_ordering"]) == (1, 1, 0)
    # Same pattern, other values: the kept ordering (first is alive, its handle busy).
    second = hinted(K, 2.0)
    assert second.analysis == "cached"
    assert analysis_cache_info()["cached_ordering"] == 1
    x = first.solve(b)
    np.testing.assert_allclose(second.solve(b), x / 2.0, rtol=0, atol=1e-12 * np.abs(x).max())
    reference = spsolve(sp.csc_array(K), b)
    assert relative(x, reference) < 1e-10


def test_dead_factorization_hands_its_analysis_on() -> None:
    K, b = noisy_system(*grid_mesh(12, False))
    x = factorize(K, "pardiso").solve(b)  # dies at once: its handle is parked
    assert analysis_cache_info()["idle_handles"] == 1
    again = factorize(3.0 * K, "pardiso")
    assert again.analysis == "cached"
    assert again.timings["analysis"] == 0.0  # numerical factorization only (phase 22)
    info = analysis_cache_info()
    assert (info["cached_handle"], info["idle_handles"]) == (1, 0)
    assert relative(3.0 * again.solve(b), x) < 1e-12


def test_results_with_and_without_cache_agree() -> None:
    K, b = noisy_system(*grid_mesh(14, True), seed=3)
    linalg.ANALYSIS_CACHE_BYTES = 0
    uncached = factorize(K, "pardiso")
    assert uncached.analysis == "computed"
    x_plain = uncached.solve(b)
    del uncached
    assert analysis_cache_info()["patterns"] == 0  # nothing kept with the cache off
    linalg.ANALYSIS_CACHE_BYTES = 64 * 2**20
    computed = hinted(K)
    by_ordering = hinted(K)
    x_computed, x_ordering = computed.solve(b), by_ordering.solve(b)
    del computed
    by_handle = hinted(K)
    assert (by_ordering.analysis, by_handle.analysis) == ("cached", "cached")
    assert analysis_cache_info()["cached_handle"] == 1
    unhinted = factorize(K, "pardiso")  # PARDISO's own ordering: its own cache entry
    assert unhinted.analysis == "computed" and analysis_cache_info()["patterns"] == 2
    for x in (x_computed, x_ordering, by_handle.solve(b), unhinted.solve(b)):
        assert relative(x, x_plain) < 1e-12


@pytest.mark.parametrize("other", ["other diagonals", "relabelled vertices"])
def test_same_size_other_connectivity_never_reuses_an_analysis(other: str) -> None:
    vertices, faces = grid_mesh(12, False)
    Ka, ba = noisy_system(vertices, faces)
    if other == "other diagonals":
        Kb, bb = noisy_system(*grid_mesh(12, True))
    else:  # an isomorphic mesh: the same surface with its vertices numbered otherwise
        order = np.random.default_rng(1).permutation(len(vertices))
        Kb, bb = noisy_system(vertices[order], np.argsort(order)[faces])
    assert Ka.shape == Kb.shape
    factorize(Ka, "pardiso").solve(ba)  # parks an analysed handle for pattern a
    other_factor = factorize(Kb, "pardiso")
    assert other_factor.analysis == "computed"
    assert analysis_cache_info()["patterns"] == 2
    assert relative(other_factor.solve(bb), spsolve(sp.csc_array(Kb), bb)) < 1e-10


def test_cache_stays_within_its_limit_lru_first() -> None:
    sizes = [8, 9, 10, 11, 12, 13]
    systems = [noisy_system(*grid_mesh(k, False)) for k in sizes]
    factorize(systems[-1][0], "pardiso")  # the largest entry (ordering + idle handle)
    linalg.release_cached_factors()  # its analysis alone
    largest = analysis_cache_info()["bytes"]
    linalg.clear_analysis_cache()
    linalg.ANALYSIS_CACHE_BYTES = int(2.5 * largest)  # room for about two patterns
    for K, b in systems:
        factorize(K, "pardiso").solve(b)
        info = analysis_cache_info()
        assert 0 < info["bytes"] <= linalg.ANALYSIS_CACHE_BYTES
    assert analysis_cache_info()["patterns"] < len(sizes)
    assert factorize(systems[-1][0], "pardiso").analysis == "cached"  # recent: kept
    assert factorize(systems[0][0], "pardiso").analysis == "computed"  # oldest: evicted


def test_idle_handles_keep_their_factor_memory_within_the_limit() -> None:
    """A parked handle keeps its numerical factor's memory (counted in the cache's bytes),
    the next factorization of the pattern refactorizes into it with the same answer, and
    the factor is what goes first: at a limit below it, or when asked to."""
    K, b = noisy_system(*grid_mesh(12, False))
    reference = spsolve(sp.csc_array(K), b)
    factorize(K, "pardiso").solve(b)
    info = analysis_cache_info()
    assert info["idle_handles"] == 1 and 0 < info["factor_bytes"] < info["bytes"]
    again = factorize(K * 1.5, "pardiso")  # new values, the kept handle and its memory
    assert again.analysis == "cached" and analysis_cache_info()["cached_handle"] == 1
    assert relative(1.5 * again.solve(b), reference) < 1e-10
    del again
    held = analysis_cache_info()
    linalg.release_cached_factors()
    after = analysis_cache_info()
    assert after["factor_bytes"] == 0 and after["idle_handles"] == 1
    assert after["bytes"] == held["bytes"] - held["factor_bytes"]
    assert factorize(K, "pardiso").analysis == "cached"  # the analysis stayed
    gc.collect()
    linalg.ANALYSIS_CACHE_BYTES = analysis_cache_info()["bytes"] - 1  # not room for both
    factorize(K * 2.0, "pardiso")
    info = analysis_cache_info()
    assert info["idle_handles"] == 1 and info["factor_bytes"] == 0
    assert 0 < info["bytes"] <= linalg.ANALYSIS_CACHE_BYTES


def test_clear_frees_everything_and_live_factors_keep_working() -> None:
    K, b = noisy_system(*grid_mesh(10, False))
    alive = factorize(K, "pardiso")
    factorize(K, "pardiso")  # parked
    linalg.clear_analysis_cache()
    info = analysis_cache_info()
    assert (info["patterns"], info["idle_handles"], info["bytes"]) == (0, 0, 0)
    assert relative(alive.solve(b), spsolve(sp.csc_array(K), b)) < 1e-10
    assert factorize(K, "pardiso").analysis == "computed"


def test_failed_factorization_is_not_parked() -> None:
    K, _ = noisy_system(*grid_mesh(10, False))
    hinted(K)  # parks one analysed handle
    indefinite = sp.csr_array(K, copy=True)
    indefinite.setdiag(-indefinite.diagonal())  # same pattern, not positive definite
    with pytest.raises(SingularSystemError):
        hinted(indefinite, assume_symmetric=True).solve(np.ones(K.shape[0]))
    assert analysis_cache_info()["idle_handles"] == 0  # the failed handle was freed
    assert hinted(K).analysis == "cached"  # the ordering is still good


@pytest.mark.parametrize("hint", [True, False])
def test_concurrent_factorizations_of_one_pattern(hint: bool) -> None:
    K, b = noisy_system(*grid_mesh(12, False))
    reference = spsolve(sp.csc_array(K), b)
    groups = np.arange(K.shape[0]) if hint else None
    # One idle handle; the other threads take the ordering (hint) or order anew (no hint).
    factorize(K, "pardiso", groups=groups)

    def work(scale: float) -> float:
        factor = factorize(scale * K, "pardiso", groups=groups)
        return relative(scale * factor.solve(b), reference)

    with ThreadPoolExecutor(4) as pool:
        errors = list(pool.map(work, [1.0, 2.0, 0.5, 4.0, 8.0, 0.25, 3.0, 5.0]))
    assert max(errors) < 1e-10


def test_unhinted_factorizations_never_give_pardiso_an_ordering() -> None:
    """Without an ordering hint PARDISO orders the matrix itself and returns nothing
    (iparm[4] = 0), computed, from an idle handle or beside a live one: a user permutation
    (iparm[4] = 1 or 2) turns its two-level factorization into the classic one, whose
    solves are slower (bench/drag_regression.py). With a hint it is given the ordering."""
    K, b = noisy_system(*grid_mesh(12, False))
    reference = spsolve(sp.csc_array(K), b)
    computed = factorize(K, "pardiso")
    beside = factorize(2.0 * K, "pardiso")  # first alive: a new analysis, no ordering kept
    assert (computed.analysis, beside.analysis) == ("computed", "computed")
    del computed
    from_idle = factorize(3.0 * K, "pardiso")
    assert from_idle.analysis == "cached" and from_idle.timings["analysis"] == 0.0
    info = analysis_cache_info()
    assert (info["computed"], info["cached_handle"], info["cached_ordering"]) == (2, 1, 0)
    for factor, scale in ((beside, 2.0), (from_idle, 3.0)):
        assert user_permutation(factor) == 0
        assert relative(scale * factor.solve(b), reference) < 1e-10
    assert user_permutation(hinted(K)) == 1


def test_reports_say_whether_the_analysis_was_cached() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    forms = fundamental_forms(mesh.vertices, mesh.faces)
    inner = forms.angles != 0
    forms.angles[inner] += np.random.default_rng(5).normal(scale=1e-3, size=inner.sum())

    def solve() -> reconstruct:
        return reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                           backend="pardiso", refine=False)

    first, second = solve(), solve()
    assert (first.report["analysis"], second.report["analysis"]) == ("computed", "cached")
    np.testing.assert_allclose(second.vertices, first.vertices, rtol=0, atol=1e-12)
    linalg.ANALYSIS_CACHE_BYTES = 0
    np.testing.assert_allclose(solve().vertices, first.vertices, rtol=0, atol=1e-12)


def test_new_handle_set_on_the_same_mesh_reuses_the_analysis() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    first = Deformer(mesh.vertices, mesh.faces, [0, 1, 2], backend="pardiso")
    assert first.system.analysis == "computed"
    del first
    second = Deformer(mesh.vertices, mesh.faces, [5, 17, 30, 41], backend="pardiso")
    assert second.system.analysis == "cached"
    target = mesh.vertices[[5, 17, 30, 41]] + [0.0, 0.0, 0.2]
    moved = second.solve(target)
    np.testing.assert_allclose(moved[[5, 17, 30, 41]], target, rtol=0, atol=1e-12)
    linalg.ANALYSIS_CACHE_BYTES = 0
    fresh = Deformer(mesh.vertices, mesh.faces, [5, 17, 30, 41], backend="pardiso")
    np.testing.assert_allclose(fresh.solve(target), moved, rtol=0, atol=1e-12)


def test_analysis_ahead_of_the_first_factorization() -> None:
    """analyze() computes and caches the analysis of a pattern from its upper triangle
    (values unread): the first factorization of that pattern then pays only its numerical
    phase and solves exactly as an unprepared one; a second analyze() finds it cached."""
    K, b = noisy_system(*grid_mesh(12, False))
    upper = sp.csr_array(sp.triu(K, format="csr"))
    upper.sort_indices()
    scrambled = upper.copy()
    scrambled.data = np.random.default_rng(0).normal(size=len(upper.data))  # not SPD
    assert linalg.analyze(scrambled, "pardiso")
    assert analysis_cache_info()["idle_handles"] == 1
    assert not linalg.analyze(upper, "pardiso")  # cached already
    prepared = factorize(upper, "pardiso", triangle="upper")
    assert prepared.analysis == "cached" and prepared.timings["analysis"] == 0.0
    assert relative(prepared.solve(b), spsolve(sp.csc_array(K), b)) < 1e-10
    assert not linalg.analyze(upper, "superlu")  # no analysis to keep


def test_a_refining_deformer_analyses_its_refinement_at_set_up() -> None:
    """Deformer(refine=True) builds its refinement (pattern included) and has PARDISO
    analyse the Gauss-Newton matrix when it is set up, so that the first refined drag's
    first factorization is numerical only."""
    V, F = grid_mesh(14, False)
    handles = np.array([0, 13, 182, 195])
    deformer = Deformer(V, F, handles, refine=True)
    assert deformer._refiner is not None
    before = analysis_cache_info()
    deformer.solve(V[handles] + [0.0, 0.0, 0.3])
    after = analysis_cache_info()
    assert deformer.last_report["factorizations"] >= 1
    assert after["computed"] == before["computed"]  # nothing analysed during the drag


def test_single_precision_factor_solves_to_float32_accuracy() -> None:
    """factorize(precision="single") factorizes and solves in float32 and returns float64:
    its answers are within float32 accuracy of the double-precision solution, but not
    exact (the precision is really used); its analysis is kept apart from double's, and a
    pickled factor comes back in single precision. Other backends ignore the precision."""
    K, b = noisy_system(*grid_mesh(12, False))
    upper = sp.csr_array(sp.triu(K, format="csr"))
    upper.sort_indices()
    exact = spsolve(sp.csc_array(K), b)
    assert linalg.analyze(upper, "pardiso", precision="single")
    single = factorize(upper, "pardiso", triangle="upper", precision="single")
    assert single.precision == "single" and single.analysis == "cached"
    x = single.solve(b)
    assert x.dtype == np.float64
    assert 1e-12 < relative(x, exact) < 1e-3
    double = factorize(upper, "pardiso", triangle="upper")
    assert double.precision == "double" and double.analysis == "computed"
    assert relative(double.solve(b), exact) < 1e-10
    assert pickle.loads(pickle.dumps(single)).precision == "single"
    assert factorize(K, "superlu", precision="single").precision == "double"
    with pytest.raises(ValueError, match="precision"):
        factorize(K, "pardiso", precision="half")
