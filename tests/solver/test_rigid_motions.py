"""solver.mesh.rigid_motions: the projection off the free rigid motions, and why the refinement
needs it (a factor used away from where it was built)."""

import numpy as np
import pytest

from solver import fundamental_forms
from solver.mesh.rigid_motions import RigidMotions
from solver.mesh.topology import build_topology
from solver.refine import FormTargets, Handles, Refiner
from tests.helpers.meshes import icosphere, load


def two_spheres() -> tuple[np.ndarray, np.ndarray]:
    """Two disjoint icospheres (two connected components), the second shifted."""
    V, F = icosphere(2)
    shift = np.array([3.0, 0.5, -1.0])
    return np.concatenate([V, V + shift]), np.concatenate([F, F + len(V)])


def rigid_basis(X: np.ndarray, dim: int) -> np.ndarray:
    """Infinitesimal rigid motions of positions X (n, dim), as columns (n * dim, k)."""
    n = len(X)
    columns = [np.tile(np.eye(dim)[a], n) for a in range(dim)]
    r = X - X.mean(axis=0)
    if dim == 3:
        columns += [np.cross(np.eye(3)[a], r).ravel() for a in range(3)]
    else:
        columns.append(np.stack([-r[:, 1], r[:, 0]], axis=1).ravel())
    return np.stack(columns, axis=1)


@pytest.mark.parametrize("dim", [3, 2])
@pytest.mark.parametrize("spheres", ["second held", "both free", "one free"])
def test_projection_removes_exactly_the_rigid_motions_of_unheld_components(dim, spheres):
    """Each unheld component loses exactly its rigid motions (one or two of them, all rows
    or some rows projected); a held one is untouched."""
    V, F = two_spheres() if spheres != "one free" else icosphere(2)
    X = V[:, :dim] + 0.05 * np.random.default_rng(0).normal(size=(len(V), dim))
    n = len(V) // 2 if spheres != "one free" else len(V)
    held = np.zeros(len(V), dtype=bool)
    if spheres == "second held":
        held[n + 3] = True  # a handle on the second sphere: its motions are not free
    free = np.ones(len(V), dtype=bool)
    motions = RigidMotions(build_topology(F, len(V)), free, held, dim)
    assert motions.active
    project = motions.at(X)
    rng = np.random.default_rng(1)
    v = rng.normal(size=len(V) * dim)
    parts = [slice(0, n)] + ([slice(n, len(V))] if spheres == "both free" else [])
    for part in parts:
        rows = slice(part.start * dim, part.stop * dim)
        v[rows] += rigid_basis(X[part], dim) @ rng.normal(size=3 if dim == 2 else 6) * 100.0
    given = v.copy()
    p = project(v)
    assert np.array_equal(v, given)  # the step given is not changed
    for part in parts:  # orthogonal to its rigid motions, and only they were removed
        rows = slice(part.start * dim, part.stop * dim)
        basis = rigid_basis(X[part], dim)
        kept, removed = p[rows], v[rows] - p[rows]
        assert np.abs(basis.T @ kept).max() < 1e-9 * np.abs(v).max()
        coefficients = np.linalg.lstsq(basis, removed, rcond=None)[0]
        assert np.abs(basis @ coefficients - removed).max() < 1e-9 * np.abs(v).max()
        assert np.abs(removed).max() > 1.0  # something was removed
    if spheres == "second held":  # the held component is untouched
        assert np.array_equal(p[n * dim:], v[n * dim:])
    assert np.allclose(project(p), p, atol=1e-12 * np.abs(v).max())  # twice: no change


def test_problems_with_handles_on_every_component_have_nothing_to_project():
    V, F = icosphere(2)
    held = np.zeros(len(V), dtype=bool)
    held[0] = True
    motions = RigidMotions(build_topology(F, len(V)), np.ones(len(V), bool), held, 3)
    assert not motions.active
    v = np.arange(len(V) * 3, dtype=float)
    assert motions.at(V)(v) is v


def test_a_factor_used_after_a_move_gives_a_descent_step_only_without_its_rotations():
    """Angles x 0.8 on the knight, no handles: the Gauss-Newton factor built at the start,
    applied to the gradient after one step, returns a huge linearized rotation that raises
    E at every step length; the same step without the factor's rigid motions lowers E."""
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    topology = build_topology(F, len(V))
    refiner = Refiner(FormTargets(topology, forms.lengths, 0.8 * forms.angles), Handles())
    assert refiner.rigid_motions.active
    X1 = V.copy()
    _, H, g1 = refiner.system.normal_equations(X1)
    factor = refiner._damped_factor(H, 1e-9)
    X2 = X1 - 0.5 * factor.solve(g1).reshape(-1, 3)  # half a Gauss-Newton step: a move
    E2, _, g2 = refiner.system.normal_equations(X2, matrix=False)
    raw = -factor.solve(g2)
    projected = -refiner.rigid_motions.at(X1)(factor.solve(g2))
    assert np.linalg.norm(raw) > 100 * np.linalg.norm(projected)
    energy = refiner.form_energy.energy
    assert all(energy(X2 + t * raw.reshape(-1, 3)) > E2 for t in (1.0, 0.5, 0.25, 0.1))
    assert energy(X2 + projected.reshape(-1, 3)) < E2
