"""The Python client's flattening of a closed mesh (issue 41): the atlas arrays over binary
and JSON bodies and as a job with per-chart progress, equal to the library's."""

from __future__ import annotations

import numpy as np
import pytest

import solver
from ffs import Client
from tests.helpers.meshes import load


@pytest.mark.parametrize("binary", [True, False])
def test_client_returns_the_librarys_atlas(server, binary):
    V, F = load("torus.off")
    library = solver.parameterize(V, F)
    with Client(server, binary=binary, timeout=120) as client:
        flat = client.parameterize(V, F)
    assert flat.charts == library.report.atlas["charts"] >= 2
    np.testing.assert_array_equal(flat.uv_faces, library.uv_faces)
    np.testing.assert_array_equal(flat.uv_vertex, library.uv_vertex)
    np.testing.assert_array_equal(flat.face_chart, library.face_chart)
    np.testing.assert_allclose(flat.texcoords, library.texcoords, atol=1e-6)
    assert np.array_equal(flat.uv_vertex[flat.uv_faces], F)
    assert flat.report["warnings"] == []


def test_client_job_reports_charts_progress(server):
    V, F = load("decimated-knight.off")
    seen = []
    with Client(server, timeout=120) as client:
        job = client.submit("parameterize", V, F)
        flat = job.result(on_progress=lambda stage, fraction: seen.append((stage, fraction)))
    assert flat.charts >= 2 and len(flat.flipped_faces) == 0
    assert "charts" in {stage for stage, _ in seen}
