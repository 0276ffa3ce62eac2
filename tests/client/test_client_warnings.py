"""The client's ``result.warnings`` against a real uvicorn (issue 43): the service returns
the report's warnings of deform and reconstruct (and the refinement's outcome), the client
exposes them; a good answer has none."""

from __future__ import annotations

import numpy as np

import ffs
from tests.helpers.meshes import load


def test_warnings_and_outcome_through_the_service(server) -> None:
    vertices, faces = load("face.off")
    with ffs.Client(server) as client:
        pulled = client.deform(vertices, faces, [0, 500], np.array([[0, 0, 0], [0, 0, 1.0]]))
        codes = [w["code"] for w in pulled.warnings]
        assert "length-error" in codes
        edges = np.unique(np.sort(np.concatenate(
            [faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)

        def lengths(v: np.ndarray) -> np.ndarray:
            return np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)

        measured = np.abs(lengths(pulled.vertices) / lengths(vertices) - 1).max()
        value = next(w["value"] for w in pulled.warnings if w["code"] == "length-error")
        assert abs(value - measured) < 1e-9
        lifted = client.deform(vertices, faces, [0, 500],
                               np.array([vertices[0], vertices[500] + [0, 0, 3.0]]))
        assert lifted.warnings == []
        assert lifted.report["refinement"]["outcome"] == "converged"
        forms = client.fundamental_forms(vertices, faces)
        hurried = client.reconstruct(forms.faces, forms.edges, forms.lengths,
                                     0.8 * forms.angles, max_seconds=1e-4)
        assert hurried.report["refinement"]["outcome"] == "not-refined"
        assert "time-limit-no-progress" in [w["code"] for w in hurried.warnings]
        flat = client.parameterize(vertices, faces)
        assert flat.warnings == [] and flat.report["warnings"] == []


def test_align_to_request_option(server) -> None:
    """``align_to`` on POST /v1/reconstruct (JSON and binary bodies, through the client):
    the answer lies on the reference and ``report.alignment`` is its measured residual; a
    reference of another size is a 422 naming ``align_to``."""
    import httpx

    vertices, faces = load("face.off")
    for binary in (True, False):
        with ffs.Client(server, binary=binary) as client:
            forms = client.fundamental_forms(vertices, faces)
            bent = client.reconstruct(forms.faces, forms.edges, forms.lengths,
                                      0.8 * forms.angles, align_to=vertices)
            distance = np.linalg.norm(bent.vertices - vertices, axis=1)
            alignment = bent.report["alignment"]
            assert abs(alignment["residual_rms"] - np.sqrt(np.mean(distance ** 2))) < 1e-9
            assert abs(alignment["residual_max"] - distance.max()) < 1e-9
            exact = client.reconstruct(forms, align_to=vertices)
            assert np.abs(exact.vertices - vertices).max() < 1e-6
    body = {"faces": forms.faces.tolist(), "edges": forms.edges.tolist(),
            "lengths": forms.lengths.tolist(), "angles": forms.angles.tolist(),
            "align_to": [[0.0, 0.0, 0.0]] * 5}
    answer = httpx.post(f"{server}/v1/reconstruct", json=body, timeout=60)
    assert answer.status_code == 422, answer.text
    assert "align_to" in answer.text and "the reference has 5 vertices" in answer.text
