"""The iterative linear path (multigrid-preconditioned CG, issue 45) against the direct one.

Both paths solve the same Eq. 5 system; the factorization is the independent truth on meshes
where both run (the iterative path is forced by ``linear_solver="iterative"``)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import trimesh

from solver import Constraints, fundamental_forms, reconstruct
from solver.immersion import ImmersionProblem
from solver.linalg.cost import PowerLaw
from solver.linalg.iterative import RULES, LinearSolverRules, available_memory
from solver.linear.system import ConstrainedSystem, near_null_space
from solver.mesh.forms import validate_forms
from solver.mesh.topology import build_topology
from tests.helpers.meshes import bumpy_grid_with_holes, load, torus_grid
from tests.helpers.real_meshes import multi_component


def _mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    if name == "icosphere":
        m = trimesh.creation.icosphere(3)
        return np.asarray(m.vertices), np.asarray(m.faces)
    if name == "capsule":
        m = trimesh.creation.capsule(height=2.0, radius=0.7, count=[24, 24])
        return np.asarray(m.vertices), np.asarray(m.faces)
    if name == "torus-grid":
        return torus_grid(24, 16)
    if name == "holes":
        return bumpy_grid_with_holes()
    if name == "two-parts":
        return multi_component()
    return load(name)


MESHES = ["icosphere", "capsule", "torus-grid", "holes", "two-parts", "torus.off", "face.off",
          "cylinder.off", "octopus-low-surface.off"]
"""Closed genus 0 and 1, open with one and several boundary loops, several components, a
coarse mesh with skinny triangles."""


def _forms(name: str, noise: float, seed: int = 0):
    V, F = _mesh(name)
    forms = fundamental_forms(V, F)
    angles = forms.angles + np.random.default_rng(seed).normal(scale=noise,
                                                                size=len(forms.angles))
    return forms, angles, len(V)


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


@pytest.mark.parametrize("name", MESHES)
@pytest.mark.parametrize("noise", [0.0, 1e-3, 2e-2])
def test_linear_answer_matches_direct(name: str, noise: float) -> None:
    forms, angles, n = _forms(name, noise)
    common = dict(refine=False, exact_shortcut=False)
    direct = reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                         n_vertices=n, linear_solver="direct", **common)
    iterative = reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                            n_vertices=n, linear_solver="iterative", **common)
    assert direct.report.solve_path == "factorization"
    assert direct.report.linear_solver["method"] == "direct"
    report = iterative.report
    assert report.solve_path == "iterative"
    assert report.backend == "none"
    solver = report.linear_solver
    assert solver["method"] == "iterative" and solver["converged"]
    # Exact forms: the tree-integrated start is the answer already (0 iterations).
    assert (1 if noise else 0) <= solver["iterations"] <= RULES.max_iterations
    assert solver["relative_residual"] <= 10 * RULES.relative_tolerance
    assert _relative(iterative.vertices, direct.vertices) < 1e-6
    assert _relative(iterative.frames, direct.frames) < 1e-6
    # The energies agree to the factorization's own accuracy (its residual check accepts
    # 1e-6; on the grid with holes the iterative answer's energy is 2e-6 lower).
    for term in ("edge", "frame"):
        assert iterative.report.energy[term] == pytest.approx(direct.report.energy[term],
                                                              rel=1e-5, abs=1e-12)


@pytest.mark.parametrize("name", ["icosphere", "torus.off", "holes"])
def test_orthonormalized_answer_matches_direct(name: str) -> None:
    forms, angles, n = _forms(name, 1e-2)
    answers = [reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                           n_vertices=n, refine=False, orthonormalize=True,
                           linear_solver=method) for method in ("direct", "iterative")]
    assert _relative(answers[1].vertices, answers[0].vertices) < 1e-6
    solver = answers[1].report.linear_solver
    assert solver["converged"] and solver["first_solve"]["converged"]


def test_constrained_answer_matches_direct() -> None:
    """Hard and soft position constraints (no anchor: the constraints fix the gauge)."""
    forms, angles, n = _forms("cylinder.off", 1e-3)
    V = load("cylinder.off")[0]
    handles = np.array([0, 100, 2000, 3000, 4500])
    constraints = Constraints(position_vertices=handles, positions=V[handles] + 0.05,
                              position_weights=np.array([np.inf, np.inf, 10.0, np.inf, 5.0]))
    answers = [reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                           n_vertices=n, refine=False, constraints=constraints,
                           linear_solver=method) for method in ("direct", "iterative")]
    assert answers[1].report.linear_solver["converged"]
    assert _relative(answers[1].vertices, answers[0].vertices) < 1e-6


def _anchored(name: str) -> tuple[ImmersionProblem, Any, np.ndarray, np.ndarray]:
    """Eq. 5 of ``name``'s forms with 1e-2 rad of noise, anchored: the problem, its anchor
    constraints, the tree-integrated unknowns and the factorization's answer."""
    forms, angles, n = _forms(name, 1e-2)
    topology, L, A = validate_forms(forms.faces, forms.edges, forms.lengths, angles, n)
    problem = ImmersionProblem(topology, L, A)
    anchor, roots = problem.anchors(np.ones(topology.n_components, dtype=bool))
    tree = problem.tree_unknowns([r["face"] for r in roots], [r["vertex"] for r in roots])
    return problem, anchor, tree, problem.system(anchor).solve(anchor.hard_values,
                                                               np.zeros((0, 3)))


def _iterative(problem: ImmersionProblem, anchor: Any, tree: np.ndarray,
               rules: LinearSolverRules) -> ConstrainedSystem:
    """The anchored system solved by CG under ``rules``."""
    return ConstrainedSystem(problem.K, anchor.hard_columns, np.zeros(0, np.int64),
                             np.zeros(0), method="iterative",
                             near_null=near_null_space(problem.topology.n_vertices, tree),
                             rules=rules)


@pytest.mark.parametrize(("name", "noise"), [("icosphere", 2e-2), ("face.off", 2e-2),
                                           ("capsule", 1e-3), ("two-parts", 1e-3)])
def test_refined_answer_matches_direct(name: str, noise: float) -> None:
    """The default (refined) answer from either linear answer: the same to the refinement's
    tolerance (its form errors and energy agree), although the iterative one, which only
    starts the refinement, is solved to ``RULES.start_tolerance`` (the report says so)."""
    forms, angles, n = _forms(name, noise)
    answers = [reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                           n_vertices=n, linear_solver=method)
               for method in ("direct", "iterative")]
    for answer in answers:
        assert answer.report.refinement["converged"]
    solved = answers[1].report.linear_solver
    assert solved["tolerance"] == RULES.start_tolerance and solved["converged"]
    assert solved["relative_residual"] <= 10 * RULES.start_tolerance
    size = np.ptp(answers[0].vertices, axis=0).max()
    assert np.abs(answers[1].vertices - answers[0].vertices).max() < 1e-3 * size
    errors = [a.report.refinement["after"]["length_error"]["max"] for a in answers]
    assert errors[1] == pytest.approx(errors[0], rel=1e-2, abs=1e-6)
    energies = [a.report.refinement["energy_after"] for a in answers]
    assert energies[1] == pytest.approx(energies[0], rel=1e-4)


def test_a_returned_linear_answer_is_solved_to_the_full_tolerance() -> None:
    """Only a linear answer that starts the refinement stops at the start's tolerance: with
    ``refine=False``, and where forms that failed the integrability check (a tolerance of
    1e-15 on exact forms) turn out reproduced by the linear answer, which is then returned,
    the solve goes on to ``relative_tolerance``."""
    forms, angles, n = _forms("capsule", 1e-3)
    linear = reconstruct(forms.faces, forms.edges, forms.lengths, angles, n_vertices=n,
                         linear_solver="iterative", refine=False).report.linear_solver
    assert linear["tolerance"] == RULES.relative_tolerance
    assert linear["relative_residual"] <= 10 * RULES.relative_tolerance
    exact, _, _ = _forms("capsule", 0.0)
    answer = reconstruct(exact.faces, exact.edges, exact.lengths, exact.angles, n_vertices=n,
                         linear_solver="iterative", integrability_tol=1e-15)
    assert answer.report.solve_path == "iterative"
    assert answer.report.integrability["integrable"] is False
    assert answer.report.refinement["reason"].startswith("exact")
    assert answer.report.linear_solver["tolerance"] == RULES.relative_tolerance


def test_non_converged_solve_is_reported() -> None:
    """One iteration cannot reach the tolerance: the answer says so (not silently wrong)."""
    problem, anchor, tree, truth = _anchored("torus.off")
    for limit, converged in ((1, False), (RULES.max_iterations, True)):
        system = _iterative(problem, anchor, tree, LinearSolverRules(max_iterations=limit))
        u = system.solve(anchor.hard_values, np.zeros((0, 3)), tree)
        report = system.linear_solver_report()
        assert report["converged"] is converged
        assert report["iterations"] == (1 if limit == 1 else report["iterations"])
        error = _relative(u, truth)
        if converged:
            assert report["relative_residual"] <= 10 * RULES.relative_tolerance
            assert error < 1e-6
        else:
            assert report["relative_residual"] > 10 * RULES.relative_tolerance
            assert error > 1e-6


@pytest.mark.parametrize("name", ["torus.off", "holes", "two-parts"])
def test_single_precision_preconditioner_keeps_the_answer(name: str) -> None:
    """The float32 hierarchy (the default) only preconditions: CG's residual is float64, so
    the answer reaches the same tolerance as with a float64 hierarchy, against the factor."""
    problem, anchor, tree, truth = _anchored(name)
    iterations = {}
    for dtype in ("float32", "float64"):
        system = _iterative(problem, anchor, tree, LinearSolverRules(preconditioner_dtype=dtype))
        u = system.solve(anchor.hard_values, np.zeros((0, 3)), tree)
        report = system.linear_solver_report()
        assert report["precision"] == dtype and report["converged"]
        assert report["relative_residual"] <= 10 * RULES.relative_tolerance
        assert _relative(u, truth) < 1e-6
        iterations[dtype] = report["iterations"]
    # Single-precision rounding of the cycle costs at most a couple of iterations.
    assert iterations["float32"] <= iterations["float64"] + 2


def test_rules_choose_by_size_and_memory() -> None:
    rules = LinearSolverRules(face_threshold=1000, direct_memory=PowerLaw(per_face=1e4))
    assert rules.choose(999) == "direct"
    assert rules.choose(1000) == "iterative"
    assert rules.choose(500, memory_bytes=4e6) == "iterative"   # 5 MB would not fit
    assert rules.choose(500, memory_bytes=6e6) == "direct"
    assert rules.choose(10**7, "direct") == "direct"
    with pytest.raises(ValueError, match="linear solver"):
        rules.choose(10, "cholesky")


def test_auto_keeps_small_meshes_direct() -> None:
    forms, angles, _ = _forms("icosphere", 1e-3)
    answer = reconstruct(forms.faces, forms.edges, forms.lengths, angles, refine=False)
    assert answer.report.solve_path == "factorization"
    assert answer.report.linear_solver["method"] == "direct"


def test_a_memory_budget_chooses_the_path() -> None:
    """``memory_budget`` (the service's FFS_MAX_REQUEST_MEMORY) replaces the machine's
    available memory in ``auto``'s choice: below the direct path's predicted peak the same
    forms are solved iteratively, above it by a factorization, to the same answer; the
    refinement's Gauss-Newton steps follow (their direct model is dearer than Eq. 5's)."""
    forms, angles, _ = _forms("capsule", 1e-3)
    n = len(forms.faces)
    direct = RULES.direct_memory.at(n)
    answers = {}
    for budget in (0.5 * direct, 2 * direct):
        answer = reconstruct(forms.faces, forms.edges, forms.lengths, angles, refine=False,
                             memory_budget=budget)
        answers[answer.report.linear_solver["method"]] = answer.vertices
        assert answer.report.solve_path == ("iterative" if budget < direct
                                            else "factorization")
    assert _relative(answers["iterative"], answers["direct"]) < 1e-6
    assert available_memory(0.5 * direct) == pytest.approx(0.5 * direct)
    from solver.refine import FormTargets, Refiner
    from solver.refine.iterative_steps import REFINEMENT_SOLVER_RULES

    targets = FormTargets(build_topology(forms.faces), forms.lengths, angles)
    refinement = REFINEMENT_SOLVER_RULES.direct_memory.at(n)
    assert Refiner(targets, linear_solver="auto",
                   memory_budget=0.9 * refinement).linear_solver == "iterative"
    assert Refiner(targets, linear_solver="auto",
                   memory_budget=1.1 * refinement).linear_solver == "direct"


@pytest.mark.parametrize("method", ["direct", "iterative"])
def test_a_released_k_is_freed_by_the_system(method: str) -> None:
    """``ImmersionProblem.system(..., release=True)`` (the last system ``reconstruct``
    builds): the problem lets go of K, which is freed once the system has its own
    constrained copy (not kept through the multigrid setup and the refinement), and the
    system solves as one built from a kept K; a later use of K assembles it again."""
    import weakref

    problem, anchor, tree, truth = _anchored("capsule")
    near_null = near_null_space(problem.topology.n_vertices, tree)
    kept = problem.system(anchor, method=method, near_null=near_null).solve(
        anchor.hard_values, np.zeros((0, 3)), tree)
    K = problem.K
    freed = weakref.ref(K)
    nnz = K.nnz
    del K
    system = problem.system(anchor, method=method, near_null=near_null, release=True)
    assert freed() is None and "K" not in problem.__dict__
    u = system.solve(anchor.hard_values, np.zeros((0, 3)), tree)
    assert _relative(u, kept) < 1e-6 and _relative(u, truth) < 1e-6
    assert problem.K.nnz == nnz
