"""POST /v1/reconstruct/vjp: the service as a remote differentiable layer, against the
library's reconstruct_vjp (and a real uvicorn on loopback)."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

import solver
from solver.mesh.io import save_mesh
from tests.helpers.meshes import load
from tests.helpers.real_meshes import CASES as REAL
from tests.helpers.service import problem
from tests.helpers.welded_meshes import CASES as WELDED


def noisy_forms():
    V, F = load("decimated-knight.off")
    forms = solver.fundamental_forms(V, F)
    rng = np.random.default_rng(0)
    angles = np.clip(forms.angles + 0.01 * rng.standard_normal(len(forms.angles)),
                     -np.pi + 1e-6, np.pi)
    return V, solver.Forms(forms.faces, forms.edges, forms.lengths, angles)


def forms_json(forms: solver.Forms) -> dict:
    return {"faces": forms.faces.tolist(), "edges": forms.edges.tolist(),
            "lengths": forms.lengths.tolist(), "angles": forms.angles.tolist()}


def test_vjp_matches_library(client):
    V, forms = noisy_forms()
    rng = np.random.default_rng(1)
    for refine in (False, None):
        G = rng.standard_normal((2, len(V), 3))
        body = {**forms_json(forms), "cotangent": G.tolist(), "options": {"refine": refine}}
        response = client.post("/v1/reconstruct/vjp", json=body)
        assert response.status_code == 200, response.text
        got = response.json()
        result, vjp = solver.reconstruct_vjp(forms.faces, forms.edges, forms.lengths,
                                             forms.angles, refine=refine)
        grad_L, grad_A = vjp(G)
        np.testing.assert_allclose(got["vertices"], result.vertices, atol=1e-9)
        scale = np.abs(grad_L).max()
        np.testing.assert_allclose(got["grad_lengths"], grad_L, atol=1e-9 * scale)
        np.testing.assert_allclose(got["grad_angles"], grad_A, atol=1e-9 * scale)
        assert got["report"]["vjp"]["mode"] == ("linear" if refine is False else "refined")


def test_vjp_refuses_a_cotangent_of_the_wrong_shape(client):
    V, forms = noisy_forms()
    body = {**forms_json(forms), "cotangent": [[0.0, 0.0, 1.0]] * (len(V) - 1)}
    response = client.post("/v1/reconstruct/vjp", json=body)
    doc = problem(response, 422, "invalid-constraint")
    assert doc["errors"][0]["field"] == "cotangent", doc


def test_vjp_over_a_real_server(live_server):
    V, forms = noisy_forms()
    g = np.zeros((len(V), 3))
    g[:, 2] = 1.0
    body = {**forms_json(forms), "cotangent": g.tolist(), "options": {"refine": False}}
    response = httpx.post(f"{live_server}/v1/reconstruct/vjp", json=body, timeout=120)
    assert response.status_code == 200, response.text
    _, vjp = solver.reconstruct_vjp(forms.faces, forms.edges, forms.lengths, forms.angles,
                                    refine=False)
    grad_L, _ = vjp(g)
    np.testing.assert_allclose(response.json()["grad_lengths"], grad_L,
                               atol=1e-9 * np.abs(grad_L).max())


REAL_FILES = [("edge-with-4-faces", False), ("cones-at-apex", None), ("duplicated-corner", False),
              ("latlong-capsule", None)]
"""Real files: non-manifold (an edge of 4 faces, two cones at one apex) and with vertices
joined by zero-length edges (welded); linear and refined answers."""


@pytest.mark.parametrize(("name", "refine"), REAL_FILES)
def test_vjp_of_a_real_files_forms_over_a_real_server(live_server, name, refine):
    """The forms POST /v1/forms answers for a non-manifold or welded file (vertex_map,
    weld_map, placement) go back to /v1/reconstruct/vjp as they are (no 422): the answer is
    /v1/reconstruct's per file vertex on the file's faces, the cotangent per file vertex,
    the gradients the library's."""
    V, F = REAL[name]() if name in REAL else WELDED[name]()[:2]
    with httpx.Client(base_url=live_server, timeout=120) as http:
        doc = http.post("/v1/forms", files={"file": (f"{name}.off", save_mesh(V, F, "off"))})
        assert doc.status_code == 200, doc.text
        forms = doc.json()
        assert "vertex_map" in forms
        rng = np.random.default_rng(4)
        forms["angles"] = (np.asarray(forms["angles"])
                           + 0.003 * rng.standard_normal(len(forms["angles"]))).tolist()
        G = rng.standard_normal((len(V), 3))
        options = {"refine": refine, "require_integrable": False}
        response = http.post("/v1/reconstruct/vjp",
                             json={**forms, "cotangent": G.tolist(), "options": options})
        assert response.status_code == 200, response.text
        got = response.json()
        plain = http.post("/v1/reconstruct", json={**forms, "options": options}).json()
    arrays = {k: np.asarray(forms[k]) for k in ("faces", "edges", "lengths", "angles",
                                                 "vertex_map")}
    result, vjp = solver.reconstruct_vjp(
        arrays["faces"], arrays["edges"], arrays["lengths"], arrays["angles"], refine=refine,
        vertex_map=arrays["vertex_map"], weld_map=forms.get("weld_map"),
        placement=forms["placement"], n_vertices=len(V))
    grad_L, grad_A = vjp(G)
    scale = np.abs(grad_L).max()
    tolerance = 1e-9 if refine is False else 1e-6   # refined: other BLAS threads
    np.testing.assert_allclose(got["grad_lengths"], grad_L, atol=tolerance * scale)
    np.testing.assert_allclose(got["grad_angles"], grad_A, atol=tolerance * scale)
    np.testing.assert_allclose(got["vertices"], result.vertices, atol=tolerance * 10)
    np.testing.assert_array_equal(got["faces"], plain["faces"])
    assert len(got["vertices"]) == len(V) and np.asarray(got["grad_lengths"]).shape == (
        len(forms["lengths"]),)
    if refine is False:   # the linear answer is /v1/reconstruct's
        np.testing.assert_allclose(got["vertices"], plain["vertices"], atol=1e-12)
    else:
        assert np.abs(np.asarray(got["vertices"]) - plain["vertices"]).max() < 1e-4 * np.ptp(V)


def test_vjp_of_a_cut_mesh_refuses_a_cotangent_per_cut_vertex(client):
    V, F = REAL["edge-with-4-faces"]()
    forms = solver.fundamental_forms(V, F)
    body = {**forms_json(forms), "vertex_map": forms.vertex_map.tolist(),
            "cotangent": [[0.0, 0.0, 1.0]] * len(forms.vertex_map)}
    doc = problem(client.post("/v1/reconstruct/vjp", json=body), 422, "invalid-constraint")
    assert doc["errors"][0]["field"] == "cotangent", doc
