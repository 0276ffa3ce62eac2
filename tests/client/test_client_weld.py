"""The Python client on meshes with zero-length edges (issue 40, solver.mesh.weld), against a
real uvicorn and in-process: the forms carry ``weld_map`` and ``dropped_faces`` (binary and
JSON bodies), reconstruct and check use them, deform, blend and flatten answer per file
vertex with welded copies at one position."""

from __future__ import annotations

import numpy as np
import pytest

import ffs
from ffs.local import Local
from tests.helpers.meshes import rigid_alignment_error
from tests.helpers.real_meshes import diagonal
from tests.helpers.welded_meshes import CASES


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "json"])
@pytest.mark.parametrize("name", ["latlong-sphere", "duplicated-corner", "repeated-index-face"])
def test_client_weld_round_trip_deform_blend(server, name, binary):
    V, F, welded, dropped = CASES[name]()
    with ffs.Client(server, binary=binary) as client:
        forms = client.fundamental_forms(V, F)
        assert len(forms.dropped_faces) == dropped
        weld_map = (np.arange(len(V)) if forms.weld_map is None
                    else np.asarray(forms.weld_map))
        assert int((weld_map != np.arange(len(V))).sum()) == welded
        rebuilt = client.reconstruct(forms)
        assert rebuilt.vertices.shape == V.shape
        assert rigid_alignment_error(rebuilt.vertices, V) < 1e-8
        np.testing.assert_array_equal(rebuilt.vertices, rebuilt.vertices[weld_map])
        report = client.check_integrability(forms)
        assert report.integrable and report.vertex_defect.shape == (len(V),)
        handles = np.unique(F[len(F) // 2])
        targets = V[handles] + [0.0, 0.0, 0.05 * diagonal(V)]
        moved = client.deform(V, F, handles, targets)
        np.testing.assert_allclose(moved.vertices[handles], targets, atol=1e-8 * diagonal(V))
        np.testing.assert_array_equal(moved.vertices, moved.vertices[weld_map])
        middle = client.interpolate(V, V * [1.0, 1.0, 1.5], F, 0.5)
        vertices = np.asarray(getattr(middle, "vertices", middle))
        assert rigid_alignment_error(vertices, V * [1.0, 1.0, 1.25]) < 0.05


def test_local_backend_keeps_the_weld():
    V, F, welded, dropped = CASES["latlong-capsule"]()
    local = Local()
    forms = local.fundamental_forms(V, F)
    assert len(forms.dropped_faces) == dropped
    rebuilt = local.reconstruct(forms)
    assert rigid_alignment_error(rebuilt.vertices, V) < 1e-8
    assert rebuilt.report["input"]["weld"]["welded_vertices"] == welded
    again = ffs.Forms.from_dict(forms.to_dict())  # the API document and back
    np.testing.assert_array_equal(again.weld_map, forms.weld_map)
    np.testing.assert_array_equal(again.dropped_faces, forms.dropped_faces)
