"""A flattening's refinement that stalls with the layout's quality targets met says it is
done; one that stalls past a target still says "partly"; the report's other fields stay what
the refinement did. The targets are checked here from the written layout itself (mean
edge-length change, mean largest corner-angle change, flipped faces), not from the report's
warnings."""

from __future__ import annotations

import numpy as np
import pytest

from solver import parameterize
from solver.core.warnings import DEFAULT_RULES
from solver.mesh.io import load_mesh_file
from solver.refine.outcomes import stalled_at_targets, with_outcome
from tests.helpers import DATA
from tests.helpers.meshes import bumpy_grid, sphere_cap


def _corner_angles(P: np.ndarray, T: np.ndarray) -> np.ndarray:
    e = [P[T[:, (k + 1) % 3]] - P[T[:, k]] for k in range(3)]
    cos = [np.sum(-e[k - 1] * e[k], 1) / np.linalg.norm(e[k - 1], axis=1)
           / np.linalg.norm(e[k], axis=1) for k in range(3)]
    return np.arccos(np.clip(np.stack(cos, 1), -1, 1))


def _targets_met(V: np.ndarray, F: np.ndarray, result) -> bool:
    """The layout's mean edge-length change, mean largest corner-angle change and flipped
    fraction within the documented thresholds (docs/service.md#warnings)."""
    uv_faces = F if result.uv_faces is None else result.uv_faces
    uv_vertex = np.arange(len(V)) if result.uv_vertex is None else result.uv_vertex
    pairs = np.sort(np.concatenate([uv_faces[:, [0, 1]], uv_faces[:, [1, 2]],
                                    uv_faces[:, [2, 0]]]), axis=1)
    pairs = np.unique(pairs, axis=0)
    flat = np.linalg.norm(result.uv[pairs[:, 1]] - result.uv[pairs[:, 0]], axis=1)
    rest = np.linalg.norm(V[uv_vertex[pairs[:, 1]]] - V[uv_vertex[pairs[:, 0]]], axis=1)
    length = np.abs(flat / rest - 1).mean()
    flat3 = np.column_stack([result.uv, np.zeros(len(result.uv))])
    angle = np.abs(_corner_angles(flat3, uv_faces) - _corner_angles(V, F)).max(axis=1).mean()
    a, b, c = (result.uv[uv_faces[:, k]] for k in range(3))
    flipped = np.mean((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0] < 0)
    return bool(length <= DEFAULT_RULES.max_flatten_length_change
                and angle <= DEFAULT_RULES.max_flatten_angle_change
                and flipped <= DEFAULT_RULES.max_flipped_fraction)


CASES = {  # name: (mesh, seams, the refinement's stop reason on it)
    "face, one chart": (lambda: load_mesh_file(DATA / "face.off"), "auto", "stalled"),
    "octopus, atlas": (lambda: load_mesh_file(DATA / "octopus-low-surface.off"), "auto",
                       "stalled"),
    "cap, one chart": (sphere_cap, "none", "stalled"),
    "bumpy grid": (lambda: bumpy_grid(20, 15), "auto", "converged"),
    "knight, atlas": (lambda: load_mesh_file(DATA / "decimated-knight.off"), "auto",
                      "converged"),
}


@pytest.mark.parametrize("case", CASES)
def test_a_stall_at_the_quality_targets_is_done(case):
    mesh, seams, stop = CASES[case]
    V, F = mesh()
    result = parameterize(V, F, seams=seams)
    report = result.report.to_dict()
    refinement = report["refinement"]
    assert refinement["stop_reason"] == stop  # the family covers both stops
    met = _targets_met(V, F, result)
    assert met == (report["warnings"] == [])
    text = refinement["outcome_text"]
    if stop == "stalled" and met:
        assert text.startswith("done: quality targets met, stalled (no further progress) "
                               f"after {refinement['iterations']} iterations"), text
        assert refinement["targets_met"] is True
    elif stop == "stalled":
        assert text.startswith("partly: stalled"), text
        assert "targets_met" not in refinement
    else:
        assert text.startswith("converged after"), text
    # What the refinement did is told as it was.
    assert refinement["converged"] == (stop == "converged")
    assert refinement["outcome"] == ("partial" if stop == "stalled" else "converged")
    assert refinement["energy_after"] < refinement["energy_before"]


def test_only_a_stall_is_told_as_done():
    """A time limit or an iteration budget is not the flattening's end: still "partly"."""
    for reason, words in (("time_limit", "time limit"), ("max_iterations", "iteration budget")):
        report = stalled_at_targets(with_outcome({
            "refined": True, "converged": False, "stop_reason": reason, "iterations": 3,
            "energy_before": 2.0, "energy_after": 1.0}))
        assert report["outcome_text"] == f"partly: {words} after 3 iterations"
        assert "targets_met" not in report
    no_progress = stalled_at_targets(with_outcome({
        "refined": True, "converged": False, "stop_reason": "stalled", "iterations": 3,
        "energy_before": 1.0, "energy_after": 1.0}))
    assert no_progress["outcome"] == "not-refined" and "targets_met" not in no_progress
