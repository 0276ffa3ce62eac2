"""Blends, means and transfers of meshes as people have them (issue 40 x issue 44): a fin, two
boxes on one edge, cones touching at their apex (non-manifold: blended on the manifold cut)
and welded meshes (a capsule with its poles repeated, a duplicated corner, a face (a, a, b)):
answered in the file's numbering, each row's report saying what was cut or welded, and over
HTTP the library's answer."""

from __future__ import annotations

import numpy as np
import pytest

import solver
from tests.helpers.meshes import rigid_alignment_error
from tests.helpers.real_meshes import box_with_fin, boxes_sharing_an_edge, cones_at_apex, diagonal
from tests.helpers.welded_meshes import duplicated_corner, latlong_capsule, repeated_index_face

CASES = {
    "box_with_fin": lambda: (*box_with_fin(), "cut"),
    "boxes_sharing_an_edge": lambda: (*boxes_sharing_an_edge(), "cut"),
    "cones_at_apex": lambda: (*cones_at_apex(), "cut"),
    "latlong_capsule": lambda: (*latlong_capsule()[:2], "weld"),
    "duplicated_corner": lambda: (*duplicated_corner()[:2], "weld"),
    "repeated_index_face": lambda: (*repeated_index_face()[:2], "weld"),
}


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(params=sorted(CASES))
def case(request):
    V, F, section = CASES[request.param]()
    return request.param, np.asarray(V, float), np.asarray(F), section


def test_blend_rows_of_one_shape_are_that_shape(case):
    _, V, F, section = case
    tall = V * [1.0, 1.0, 1.4]
    moved = (V * [1.2, 1.0, 1.0]) @ _rotation(0.4).T + 3.0  # a stretched copy elsewhere
    result = solver.blend([V, tall, moved], [[1, 0, 0], [0, 1, 0], [0.4, 0.3, 0.3]], F)
    assert result.vertices.shape == (3, len(V), 3)
    np.testing.assert_array_equal(result.faces, F)
    size = diagonal(V)
    used = np.unique(F)
    assert rigid_alignment_error(result.vertices[0][used], V[used]) < 1e-6 * size
    assert rigid_alignment_error(result.vertices[1][used], tall[used]) < 1e-6 * size
    assert np.isfinite(result.vertices).all()
    for report in result.reports:
        assert section in report["input"], report["input"]
        assert report["refinement"].get("converged", True), report["refinement"]
    if section == "cut":  # copies of a file vertex agree for exact rows
        assert result.reports[0]["input"]["cut"]["max_spread"] < 1e-6 * size


def test_mean_and_transfer_on_a_cut_or_welded_mesh(case):
    _, V, F, _ = case
    size = diagonal(V)
    used = np.unique(F)
    assert rigid_alignment_error(solver.mean([V, V + 1.0, V], F)[used], V[used]) < 1e-6 * size
    tall = V * [1.0, 1.0, 1.5]
    same = solver.transfer(V, tall, V, F)
    assert rigid_alignment_error(same[used], tall[used]) < 1e-6 * size
