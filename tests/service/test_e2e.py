"""End to end against a real uvicorn on loopback: a mesh upload run as a job to a validated
GLB, and 20 simultaneous requests of mixed sizes."""

from __future__ import annotations

import asyncio
import io
import time

import httpx
import numpy as np
import trimesh

import solver
from tests.helpers import DATA
from tests.helpers.aio import run as run_async
from tests.helpers.gltf_validator import validate_gltf
from tests.helpers.meshes import bumpy_grid, icosphere, load
from tests.helpers.service import forms_json, mesh_json, rigid_error


def test_upload_job_progress_and_glb(live_server):
    data = (DATA / "face.off").read_bytes()
    with httpx.Client(base_url=live_server, timeout=30) as http:
        response = http.post("/v1/jobs", data={"operation": "reconstruct", "color": "defect",
                                               "options": '{"orthonormalize": true}'},
                             files={"file": ("face.off", data, "application/octet-stream")})
        assert response.status_code == 202, response.text
        location = response.headers["location"]
        seen, deadline = [], time.monotonic() + 60
        while time.monotonic() < deadline:
            status = http.get(location).json()
            seen.append(status)
            if status["status"] not in ("queued", "running"):
                break
            time.sleep(0.01)
        assert status["status"] == "succeeded", status
        assert set(status["progress"]["stages"].values()) == {1.0}
        assert {"validate", "assemble", "factorize", "solve", "encode"} <= set(status["timings"])
        fractions = [s["progress"]["fraction"] for s in seen]
        assert fractions == sorted(fractions)

        glb = http.get(f"{location}/result", params={"color": "defect"},
                       headers={"accept": "model/gltf-binary"})
        assert glb.status_code == 200 and glb.headers["content-type"] == "model/gltf-binary"
        report = validate_gltf(glb.content, "glb")
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
        assert report["info"]["totalVertexCount"] == 1180
        scene = trimesh.load(io.BytesIO(glb.content), file_type="glb", process=False)
        mesh = next(iter(scene.geometry.values()))
        V, F = load("face.off")
        forms = solver.fundamental_forms(V, F)
        want = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                  orthonormalize=True, n_vertices=len(V),
                                  placement=forms.placement)  # an upload's parts stay put
        np.testing.assert_allclose(mesh.vertices, want.vertices, atol=1e-5)
        assert rigid_error(mesh.vertices, V) < 1e-4
        assert b'"COLOR_0"' in glb.content[:4096]  # the defect colour ramp

        metrics = http.get("/metrics").text
        assert 'ffs_http_requests_total{method="POST",route="/v1/jobs",status="202"}' in metrics


def _workload():
    """20 requests of mixed sizes with their expected results (library calls)."""
    requests = []
    for i in range(20):
        kind = i % 4
        if kind == 0:
            V, F = icosphere(1 + i % 4)  # 80 .. 5120 faces
            forms = solver.fundamental_forms(V, F)
            want = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                      placement=forms.placement)
            requests.append(("/v1/reconstruct", forms.to_dict(), "vertices", want.vertices))
        elif kind == 1:
            V, F = load("decimated-knight.off") if i % 8 == 1 else icosphere(2)
            want = solver.fundamental_forms(V, F).angles
            requests.append(("/v1/forms", mesh_json(V, F), "angles", want))
        elif kind == 2:
            V, F = bumpy_grid(4 + i, 3 + i // 2)
            handles, targets = [0, len(V) - 1], V[[0, -1]] + [[0, 0, 0], [0, 0, 0.2]]
            want = solver.deform(V, F, handles, targets).vertices
            body = {**mesh_json(V, F), "handles": [
                {"vertex": h, "position": p.tolist()} for h, p in zip(handles, targets,
                                                                      strict=True)]}
            requests.append(("/v1/deform", body, "vertices", want))
        else:
            V, F = load("face.off") if i % 8 == 3 else bumpy_grid(6, 5)
            requests.append(("/v1/parameterize", mesh_json(V, F), "uv",
                             solver.parameterize(V, F).uv))
    return requests


def test_twenty_simultaneous_requests(live_server):
    work = _workload()
    assert len(work) == 20

    async def run():
        limits = httpx.Limits(max_connections=20)
        async with httpx.AsyncClient(base_url=live_server, timeout=120, limits=limits) as http:
            return await asyncio.gather(*(http.post(path, json=body)
                                          for path, body, _, _ in work))

    responses = run_async(run())
    for (path, _, key, want), response in zip(work, responses, strict=True):
        assert response.status_code == 200, (path, response.text[:300])
        # deform and parameterize refine nonlinearly by default: the iterations stop at their
        # tolerance, and the worker's BLAS threads differ from this process's.
        atol = 1e-6 if path in ("/v1/deform", "/v1/parameterize") else 1e-8
        np.testing.assert_allclose(response.json()[key], want, atol=atol, err_msg=path)


def test_forms_reconstruct_roundtrip_over_http(live_server):
    V, F = icosphere(3)
    with httpx.Client(base_url=live_server, timeout=60) as http:
        forms = http.post("/v1/forms", json=mesh_json(V, F)).json()
        placement = forms.pop("placement")  # each part's pose (issue 40): one part here
        assert forms == {k: np.asarray(v).tolist() for k, v in forms_json(V, F).items()}
        # one part, anchored at the face the library picks (its largest)
        assert placement == solver.fundamental_forms(V, F).placement.to_dict()
        forms["placement"] = placement
        rebuilt = http.post("/v1/reconstruct", json=forms).json()
    assert rigid_error(rebuilt["vertices"], V) < 1e-7


def _mean_length_ratio(doc: dict, edges: np.ndarray, target: np.ndarray) -> float:
    X = np.asarray(doc["vertices"])
    return float(np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1).mean()
                 / target.mean())


def test_refine_option_over_http_on_non_integrable_forms(live_server):
    V, F = load("decimated-knight.off")
    forms = solver.fundamental_forms(V, F)
    body = {**forms.to_dict(), "angles": (forms.angles * 0.8).tolist()}  # not integrable
    with httpx.Client(base_url=live_server, timeout=120) as http:
        default = http.post("/v1/reconstruct", json=body)
        linear = http.post("/v1/reconstruct", json={**body, "options": {"refine": False}})
    assert default.status_code == 200 and linear.status_code == 200, (default.text,
                                                                      linear.text)
    refined, plain = default.json(), linear.json()
    assert refined["report"]["refinement"]["refined"] is True
    assert plain["report"]["refinement"]["refined"] is False
    kept = _mean_length_ratio(refined, forms.edges, forms.lengths)
    shrunk = _mean_length_ratio(plain, forms.edges, forms.lengths)
    assert abs(kept - 1) < 0.02, kept  # the nearest surface keeps the lengths
    assert shrunk < 0.9, shrunk  # the linear answer of Eq. 5 shrinks bent forms
