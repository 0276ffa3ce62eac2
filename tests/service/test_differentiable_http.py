"""POST /v1/reconstruct/vjp: the service as a remote differentiable layer, against the
library's reconstruct_vjp (and a real uvicorn on loopback)."""

from __future__ import annotations

import httpx
import numpy as np

import solver
from tests.helpers.meshes import load
from tests.helpers.service import problem


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
