"""Refiner.retarget: a refiner whose targets are replaced in place is the refiner built for
the new targets (energy, Gauss-Newton system, reports, runs), and refuses targets of
another structure (other cap faces, needle ties). The truth is a refiner built from
scratch for the same targets, and :func:`form_residuals` for the reports."""

import numpy as np
import pytest

from solver import fundamental_forms
from solver.mesh.topology import build_topology
from solver.refine import FormTargets, Handles, Refiner, form_residuals
from tests.helpers.meshes import (
    bumpy_grid,
    load,
    with_cap_faces,
    with_noisy_angles,
    with_tiny_edges,
)


def warped(V: np.ndarray, amount: float) -> np.ndarray:
    """A smooth non-rigid map of ``V`` (n, 3): lengths change by a few percent."""
    size = np.ptp(V, axis=0).max()
    return V + amount * size * np.sin(2.0 * V[:, [1, 2, 0]] / size)


def knight():
    return load("decimated-knight.off")


def knight_caps_needles():
    V, F = knight()
    return with_tiny_edges(with_cap_faces(V, F, 5, height=1e-6), F, count=10)


def handles_of(V: np.ndarray) -> Handles:
    return Handles(fixed=np.arange(0, 30, 3), soft_vertices=np.array([40, 50]),
                   soft_positions=V[[40, 50]] + 0.01, soft_weights=np.array([2.0, 3.0]),
                   frame_faces=np.array([7, 8]),
                   frame_edges=np.random.default_rng(3).normal(size=(2, 2, 3)),
                   frame_weights=np.array([1.0, 5.0]))


CASES = {
    "knight": (knight, {}, False),
    "knight, caps and needles": (knight_caps_needles, {}, False),
    "knight, area weights, handles": (knight, {"weighting": "area", "angle_weight": 0.3},
                                      True),
    "bumpy grid": (bumpy_grid, {"angle_weight": 2.0}, False),
}


def targets_of(V, F, topology, options, noisy=False):
    forms = fundamental_forms(V, F)
    if noisy:
        forms = with_noisy_angles(forms, seed=2)
    return FormTargets(topology, forms.lengths, forms.angles, **options)


@pytest.mark.parametrize("case", list(CASES))
def test_retargeted_refiner_is_the_refiner_of_the_new_targets(case):
    make, options, with_handles = CASES[case]
    V, F = make()
    topology = build_topology(F, len(V))
    first = targets_of(V, F, topology, options)
    second = targets_of(warped(V, 0.02), F, topology, options, noisy=True)
    handles = handles_of(V) if with_handles else None
    refiner = Refiner(first, handles)
    fresh = Refiner(second, handles)
    caps = len(fresh.form_energy.caps.faces), len(fresh.form_energy.ties)
    if case.startswith("knight, caps"):
        assert caps[0] >= 5 and caps[1] >= 10  # the structure the values live on
    assert refiner.retarget(second)
    X = warped(V, 0.01)
    assert refiner.energy(X) == pytest.approx(fresh.energy(X), rel=1e-13)
    refiner.form_energy.tie(X)
    ours, theirs = refiner.system.normal_equations(X), fresh.system.normal_equations(X)
    assert ours[0] == pytest.approx(theirs[0], rel=1e-13)
    assert np.allclose(ours[1].data, theirs[1].data, rtol=1e-12, atol=0)
    assert np.allclose(ours[2], theirs[2], rtol=1e-12, atol=1e-14 * np.abs(theirs[2]).max())
    truth = form_residuals(X, topology, second.lengths, second.angles)
    report = refiner.form_energy.report(X)  # the residuals the system just computed
    for kind in ("length_error", "angle_error"):
        for key in ("mean", "rms", "max", "p95"):
            assert report[kind][key] == pytest.approx(truth[kind][key], rel=1e-12, abs=1e-15)
    a, b = refiner.run(V), fresh.run(V)
    assert a.report["iterations"] == b.report["iterations"]
    assert np.allclose(a.vertices, b.vertices, rtol=0, atol=1e-12 * np.ptp(V))
    after = form_residuals(a.vertices, topology, second.lengths, second.angles)
    assert a.report["after"]["angle_error"]["max"] == pytest.approx(
        after["angle_error"]["max"], rel=1e-12, abs=1e-15)
    start = refiner.form_energy.placed(V, own=True)  # needles on their lengths, as a run's
    assert a.report["before"]["length_error"]["mean"] == pytest.approx(
        form_residuals(start, topology, second.lengths, second.angles)["length_error"]["mean"],
        rel=1e-12)


def test_planar_retarget():
    """A planar fit (dim 2, area term): the retargeted refiner runs as the fresh one."""
    V, F = bumpy_grid()
    topology = build_topology(F, len(V))
    forms = [fundamental_forms(W, F) for W in (V, warped(V, 0.03))]
    first, second = (FormTargets(topology, f.lengths, np.zeros_like(f.lengths),
                                 area_weight=1.0) for f in forms)
    refiner, fresh = Refiner(first, dim=2), Refiner(second, dim=2)
    assert refiner.retarget(second)
    start = V[:, :2] * 0.9
    a, b = refiner.run(start), fresh.run(start)
    assert a.report["iterations"] == b.report["iterations"]
    assert np.allclose(a.vertices, b.vertices, rtol=0, atol=1e-12)


@pytest.mark.parametrize("change", ["cap", "needle", "angle weight"])
def test_retarget_refuses_another_structure(change):
    """Targets with one more cap face or needle edge, or angles that no longer weigh, are
    not swapped in: retarget returns False and the refiner keeps its targets."""
    V, F = knight()
    topology = build_topology(F, len(V))
    first = targets_of(V, F, topology, {})
    refiner = Refiner(first)
    X = warped(V, 0.01)
    energy = refiner.energy(X)
    if change == "cap":
        W = with_cap_faces(V, F, 1, height=1e-5)
    elif change == "needle":  # one edge's end moved next to its start: 1e-4 of its length
        i, j = topology.edges[0]
        W = V.copy()
        W[j] = V[i] + 1e-4 * (V[j] - V[i])
    else:
        W = V
    other = targets_of(W, F, topology, {"angle_weight": 0.0} if change == "angle weight"
                       else {})
    assert not refiner.retarget(other)
    assert refiner.energy(X) == energy
    assert refiner.targets is first
