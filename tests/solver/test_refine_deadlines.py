"""Time limits of the refinement (solver.refine): it stops before a factorization it expects
to end past the limit, returns its best iterate, and reports why."""

import numpy as np

from solver import fundamental_forms, reconstruct
from solver.mesh.topology import build_topology
from solver.refine import FormTargets, Handles, Refiner
from tests.helpers.meshes import load


def knight_x08() -> tuple[np.ndarray, Refiner]:
    """The knight's rest positions as a start, and a refiner towards its angles x 0.8."""
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    targets = FormTargets(build_topology(F, len(V)), forms.lengths, 0.8 * forms.angles)
    return V, Refiner(targets, Handles())


def test_an_expected_factorization_past_the_limit_is_not_started():
    """With an estimate of 10 s per factorization and 5 s left, the run does not start its
    first one: it returns the start, reported as stopped at the time limit; without the
    estimate the same run factorizes and converges within the same 5 s."""
    V, refiner = knight_x08()
    refiner.expect_refresh(10.0)
    stopped = refiner.run(V, time_limit=5.0)
    report = stopped.report
    assert report["stop_reason"] == "time_limit" and not report["converged"]
    assert report["iterations"] == report["factorizations"] == 0
    assert np.array_equal(stopped.vertices, V)
    assert report["energy_after"] == report["energy_before"]
    assert refiner.can_resume

    V, fresh = knight_x08()
    done = fresh.run(V, time_limit=5.0)
    assert done.report["converged"] and done.report["factorizations"] >= 1
    assert done.report["energy_after"] < 0.9 * done.report["energy_before"]


def test_a_measured_factorization_replaces_the_estimate():
    """Once a run has timed a factorization, that time (not the estimate) decides: a tiny
    estimate given afterwards changes nothing, and a limit below the measured time stops a
    new run before its first factorization."""
    V, refiner = knight_x08()
    refiner.run(V)
    measured = refiner._iteration_seconds["refresh"]
    assert measured is not None and measured > 0
    refiner.expect_refresh(1e-9)
    assert refiner._iteration_seconds["refresh"] == measured
    stopped = refiner.run(V, time_limit=0.5 * measured)
    assert stopped.report["stop_reason"] == "time_limit"
    assert stopped.report["factorizations"] == 0


def test_a_reconstruction_out_of_time_answers_its_start_not_worse():
    """reconstruct with a budget spent by the linear answer: the refined answer is the
    refinement's start (the layout fit), reported as stopped at the time limit, with an
    energy no higher than the start's."""
    V, F = load("decimated-knight.off")
    forms = fundamental_forms(V, F)
    result = reconstruct(forms.faces, forms.edges, forms.lengths, 0.8 * forms.angles,
                         max_seconds=1e-6)
    report = result.report["refinement"]
    assert report["refined"] and report["stop_reason"] == "time_limit"
    assert report["iterations"] == 0 and report["energy_after"] == report["energy_before"]
    assert np.isfinite(result.vertices).all() and result.vertices.shape == V.shape
