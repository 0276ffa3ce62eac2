"""Honest outcomes (issue 43): a refinement report says whether it converged, stopped partly
(and why, after how many iterations) or did not refine; answers past the documented
thresholds of :class:`solver.core.warnings.WarningRules` carry ``warnings`` whose values are the
errors measured independently on the returned shapes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import solver
from solver.core.warnings import (
    DEFAULT_RULES,
    WarningRules,
    flattening_warnings,
    refinement_warnings,
)
from solver.mesh.topology import build_topology
from solver.refine import FormTargets, refine
from solver.refine.outcomes import not_refined, outcome_text, refinement_outcome
from tests.helpers import REPO

DATA = REPO / "tests" / "data"


def _face() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.load(DATA / "face.off", process=False)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)


def _max_length_error(vertices: np.ndarray, rest: np.ndarray, faces: np.ndarray) -> float:
    """max |l / L - 1| over the mesh's edges, from the positions alone."""
    edges = np.unique(np.sort(np.concatenate(
        [faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    now = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    before = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    return float(np.abs(now / before - 1).max())


def test_converged_refinement_says_so() -> None:
    vertices, faces = _face()
    forms = solver.fundamental_forms(vertices, faces)
    result = solver.reconstruct(forms.faces, forms.edges, forms.lengths, 0.8 * forms.angles)
    refinement = result.report["refinement"]
    assert refinement["refined"] and refinement["converged"]
    assert refinement["outcome"] == "converged"
    assert refinement["outcome_text"] == f"converged after {refinement['iterations']} " \
        "iterations"


def test_time_limit_before_any_step_is_not_refined_and_warns() -> None:
    vertices, faces = _face()
    forms = solver.fundamental_forms(vertices, faces)
    result = solver.reconstruct(forms.faces, forms.edges, forms.lengths, 0.8 * forms.angles,
                                max_seconds=1e-4)
    refinement = result.report["refinement"]
    assert refinement["stop_reason"] == "time_limit" and refinement["iterations"] == 0
    assert refinement["energy_after"] == refinement["energy_before"]
    assert refinement["outcome"] == "not-refined"
    assert refinement["outcome_text"] == "not refined: time limit before the first iteration"
    codes = {w["code"]: w for w in result.report["warnings"]}
    assert "time-limit-no-progress" in codes and codes["time-limit-no-progress"]["value"] == 1.0


def test_iteration_budget_after_one_step_is_partial() -> None:
    vertices, faces = _face()
    forms = solver.fundamental_forms(vertices, faces)
    start = vertices + np.random.default_rng(0).normal(0, 0.5, vertices.shape)
    targets = FormTargets(build_topology(faces, len(vertices)), forms.lengths, forms.angles)
    fit = refine(start, targets, max_iterations=1)
    assert fit.report["iterations"] == 1 and not fit.report["converged"]
    assert fit.report["energy_after"] < fit.report["energy_before"]
    assert fit.report["outcome"] == "partial"
    assert fit.report["outcome_text"] == "partly: iteration budget after 1 iteration"


def test_time_limit_after_two_iterations_is_partial_without_the_no_progress_warning() -> None:
    """The time limit runs out after the second accepted step (the progress callback waits
    out the budget there, as a loaded machine would): the answer is refined partly, says
    so with the stop reason and the count, and carries no time-limit-no-progress warning."""
    import time

    from solver.core.budget import Budget

    vertices, faces = _face()
    forms = solver.fundamental_forms(vertices, faces)
    start = vertices + np.random.default_rng(0).normal(0, 0.5, vertices.shape)
    targets = FormTargets(build_topology(faces, len(vertices)), forms.lengths, forms.angles)
    budget = Budget(3.0)
    steps: list[float] = []

    def progress(stage: str, fraction: float) -> None:
        steps.append(fraction)
        if len(steps) == 2:
            time.sleep(budget.left() or 0.0)

    fit = refine(start, targets, time_limit=budget, progress=progress)
    report = fit.report
    assert len(steps) == 2 and report["stop_reason"] == "time_limit"
    assert report["iterations"] >= 1 and not report["converged"]
    assert report["energy_after"] < report["energy_before"]
    assert report["outcome"] == "partial"
    count = report["iterations"]
    assert report["outcome_text"] == (
        f"partly: time limit after {count} iteration{'' if count == 1 else 's'}")
    assert "time-limit-no-progress" not in [w.code for w in refinement_warnings(report) if w]


def test_outcome_of_a_refinement_that_did_not_run() -> None:
    report = not_refined("disabled (refine=false)")
    assert refinement_outcome(report) == "not-refined"
    assert outcome_text(report) == "not refined: disabled (refine=false)"
    vertices, faces = _face()
    forms = solver.fundamental_forms(vertices, faces)
    result = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles)
    assert result.report["refinement"]["outcome"] == "not-refined"  # exact: nothing to do
    assert result.report["warnings"] == []


def test_deformation_past_the_length_limit_warns_with_the_measured_error() -> None:
    vertices, faces = _face()
    # The old README example: two vertices 79 units apart pinned 1 unit apart.
    moved = solver.deform(vertices, faces, [0, 500], np.array([[0, 0, 0], [0, 0, 1.0]]))
    found = {w["code"]: w for w in moved.report["warnings"]}
    measured = _max_length_error(moved.vertices, vertices, faces)
    assert found["length-error"]["value"] == pytest.approx(measured, rel=1e-9)
    assert found["length-error"]["limit"] == DEFAULT_RULES.max_length_error
    assert f"{measured:.1%}" in found["length-error"]["message"]
    # Scaled to the mesh (the README's example now): 3 units on a 181-unit face, no warning.
    lifted = solver.deform(vertices, faces, [0, 500],
                           np.array([vertices[0], vertices[500] + [0, 0, 3.0]]))
    assert _max_length_error(lifted.vertices, vertices, faces) < 0.05
    assert lifted.report["warnings"] == []


def test_flattening_warnings_measure_flips_and_lengths() -> None:
    vertices, faces = _face()
    flat = solver.parameterize(vertices, faces)
    uv = flat.uv
    e1, e2 = uv[faces[:, 1]] - uv[faces[:, 0]], uv[faces[:, 2]] - uv[faces[:, 0]]
    flips = int(((e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 0).sum())
    edges = solver.fundamental_forms(vertices, faces).edges
    change = np.abs(np.linalg.norm(uv[edges[:, 1]] - uv[edges[:, 0]], axis=1)
                    / np.linalg.norm(vertices[edges[:, 1]] - vertices[edges[:, 0]], axis=1) - 1)
    mean = float(change.mean())
    strict = WarningRules(max_flipped_fraction=-1.0, max_flatten_length_change=mean / 2)
    found = {w.code: w for w in flattening_warnings(
        flips, len(faces), mean, 0.0, flat.report["refinement"], rules=strict) if w}
    assert found["flipped-faces"].value == flips / len(faces)
    assert found["length-distortion"].value == pytest.approx(mean)
    # The defaults: the face's mean length change is within the flattening limit, no flips.
    assert mean < DEFAULT_RULES.max_flatten_length_change and flips == 0
    assert flat.report["warnings"] == []


def test_angle_warning_in_radians_and_degrees() -> None:
    found = [w for w in refinement_warnings(
        {"after": {"length_error": {"max": 0.01}, "angle_error": {"max": 0.5}}}) if w]
    assert [w.code for w in found] == ["angle-error"]
    assert "0.5 rad (28.6°; limit 0.1 rad)" in found[0].message


@pytest.mark.parametrize(("name", "outcome"), [("torus.off", "converged"),
                                               ("octopus-low-surface.off", "partial")])
def test_an_atlas_says_what_its_charts_refinements_did(name: str, outcome: str) -> None:
    """An atlas's refinement is its charts' refinements told as one: the torus's 15 charts
    all converge (the report said "converged after 0 iterations"), one of the octopus's
    charts stalls (it said "not refined: None before the first iteration" although 39
    charts were refined and the layout's energy fell)."""
    mesh = trimesh.load(DATA / name, process=False)
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    report = solver.parameterize(V, F).report
    refinement = report["refinement"]
    assert refinement["charts"] > 1 and refinement["charts_refined"] >= 1
    assert refinement["refined"] and refinement["iterations"] >= refinement["charts_refined"]
    assert refinement["energy_after"] < refinement["energy_before"]
    assert refinement["outcome"] == outcome
    counts = f"({refinement['charts_refined']} of {refinement['charts']} charts refined"
    if outcome == "converged":
        assert refinement["outcome_text"] == (
            f"converged after {refinement['iterations']} iterations {counts})")
    else:
        unconverged = refinement["charts_unconverged"]
        assert unconverged >= 1 and refinement["stop_reason"] != "converged"
        # A stall with the layout's quality targets met (no warning) is the end: done.
        done = refinement["stop_reason"] == "stalled" and report["warnings"] == []
        assert refinement["outcome_text"].startswith(
            "done: quality targets met, stalled" if done else "partly: ")
        assert refinement["outcome_text"].endswith(f"{counts}, {unconverged} not converged)")
        assert "None" not in refinement["outcome_text"]
    linear = solver.parameterize(V, F, refine=False).report["refinement"]
    assert linear["outcome"] == "not-refined"
    assert linear["outcome_text"] == f"not refined: disabled (refine=false) " \
        f"({linear['charts']} charts)"
    hurried = solver.parameterize(V, F, max_seconds=1e-6).report
    refinement = hurried["refinement"]
    assert refinement["outcome"] == "not-refined" and refinement["iterations"] == 0
    assert refinement["outcome_text"] == "not refined: time limit before the first " \
        f"iteration ({refinement['charts']} charts)"
    assert "time-limit-no-progress" in [w["code"] for w in hurried["warnings"]]
