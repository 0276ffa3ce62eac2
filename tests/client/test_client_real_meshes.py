"""The Python client on meshes as they come (issue 40), against a real uvicorn: the forms
of a non-manifold, multi-part mesh carry the vertex map and placement, and reconstruct and
check use them (binary and JSON bodies); deform and blend answer per file vertex."""

from __future__ import annotations

import numpy as np
import pytest

import ffs
from tests.helpers.meshes import rigid_alignment_error
from tests.helpers.real_meshes import CASES, diagonal


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "json"])
@pytest.mark.parametrize("name", ["edge-with-4-faces", "cones-at-apex", "multi-component"])
def test_client_round_trip_and_deform(server, name, binary):
    V, F = CASES[name]()
    with ffs.Client(server, binary=binary) as client:
        forms = client.fundamental_forms(V, F)
        assert forms.placement is not None
        assert (forms.vertex_map is not None) == (name != "multi-component")
        rebuilt = client.reconstruct(forms)
        assert rebuilt.vertices.shape == V.shape and (rebuilt.faces == F).all()
        assert rigid_alignment_error(rebuilt.vertices, V) < 1e-8
        report = client.check_integrability(forms)
        assert report.integrable and report.vertex_defect.shape == (len(V),)
        handles = np.array([int(F[0, 0]), int(F[-1, 1])])
        targets = V[handles] + [0.0, 0.0, 0.05 * diagonal(V)]
        moved = client.deform(V, F, handles, targets)
        np.testing.assert_allclose(moved.vertices[handles], targets, atol=1e-8 * diagonal(V))
