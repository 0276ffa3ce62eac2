"""Content negotiation: JSON, GLB and glTF for every mesh result, colour ramps, gzip."""

from __future__ import annotations

import base64
import gzip
import io
import json
import struct

import numpy as np
import pytest
import trimesh

from service.api.problems import ProblemError
from service.http.negotiation import negotiate
from tests.helpers.gltf_validator import validate_gltf
from tests.helpers.meshes import bumpy_grid, icosphere, load
from tests.helpers.service import forms_json, mesh_json


def _glb_json(data: bytes) -> dict:
    magic, version, total = struct.unpack_from("<III", data, 0)
    assert magic == 0x46546C67 and version == 2 and total == len(data)
    length, kind = struct.unpack_from("<II", data, 12)
    assert kind == 0x4E4F534A
    return json.loads(data[20:20 + length])


def _positions(data: bytes, kind: str) -> np.ndarray:
    scene = trimesh.load(io.BytesIO(data), file_type=kind, process=False)
    mesh = next(iter(scene.geometry.values())) if isinstance(scene, trimesh.Scene) else scene
    return np.asarray(mesh.vertices)


def _valid(data: bytes, kind: str) -> dict:
    report = validate_gltf(data, kind)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    return report


def _mesh_requests():
    V, F = bumpy_grid()
    W = V.copy()
    W[:, 2] *= 2
    return {
        "reconstruct": (forms_json(V, F), len(V)),
        "deform": ({**mesh_json(V, F), "handles": [{"vertex": 0, "position": [0, 0, 0.2]}]},
                   len(V)),
        "parameterize": (mesh_json(V, F), len(V)),
        "interpolate": ({"vertices_a": V.tolist(), "vertices_b": W.tolist(),
                         "faces": F.tolist(), "t": 0.5}, len(V)),
    }


@pytest.mark.parametrize("operation", ["reconstruct", "deform", "parameterize", "interpolate"])
def test_every_mesh_endpoint_speaks_json_glb_and_gltf(client, operation):
    body, n = _mesh_requests()[operation]
    as_json = client.post(f"/v1/{operation}", json=body)
    assert as_json.status_code == 200 and as_json.headers["content-type"] == "application/json"
    if operation == "parameterize":  # the 3D mesh, seam vertices duplicated, with uv
        expected = np.asarray(body["vertices"])[as_json.json()["uv_vertex"]]
    else:
        expected = np.asarray(as_json.json()["vertices"])

    glb = client.post(f"/v1/{operation}", json=body, headers={"accept": "model/gltf-binary"})
    assert glb.status_code == 200, glb.text
    assert glb.headers["content-type"] == "model/gltf-binary"
    report = _valid(glb.content, "glb")
    assert report["info"]["totalVertexCount"] == n
    positions = _positions(glb.content, "glb")
    assert positions.shape == (n, 3)
    np.testing.assert_allclose(positions[:, : expected.shape[1]], expected, atol=1e-5)

    gltf = client.post(f"/v1/{operation}", json=body, headers={"accept": "model/gltf+json"})
    assert gltf.status_code == 200, gltf.text
    assert gltf.headers["content-type"] == "model/gltf+json"
    doc = gltf.json()
    assert doc["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")
    base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    _valid(gltf.content, "gltf")


def test_glb_coloured_by_defect_and_distortion(client):
    V, F = icosphere(2)
    forms = forms_json(V, F)
    forms["angles"][0] += 0.1
    glb = client.post("/v1/reconstruct", params={"color": "defect"}, json=forms,
                      headers={"accept": "model/gltf-binary"})
    assert glb.status_code == 200, glb.text
    attributes = _glb_json(glb.content)["meshes"][0]["primitives"][0]["attributes"]
    assert "COLOR_0" in attributes
    _valid(glb.content, "glb")

    V, F = bumpy_grid()
    body = {**mesh_json(V, F), "handles": [{"vertex": 0, "position": [0, 0, 0.3]}]}
    gltf = client.post("/v1/deform", params={"color": "distortion"}, json=body,
                       headers={"accept": "model/gltf+json"})
    assert "COLOR_0" in gltf.json()["meshes"][0]["primitives"][0]["attributes"]
    _valid(gltf.content, "gltf")


def test_vertex_order_survives_into_the_glb(client):
    V, F = load("decimated-knight.off")
    body = {**mesh_json(V, F), "handles": [{"vertex": int(v), "position": V[v].tolist()}
                                           for v in range(0, len(V), 50)]}
    glb = client.post("/v1/deform", json=body, headers={"accept": "model/gltf-binary"})
    np.testing.assert_allclose(_positions(glb.content, "glb"), V, atol=1e-5)


@pytest.mark.parametrize(("accept", "expected"), [
    (None, "json"), ("", "json"), ("*/*", "json"), ("application/json", "json"),
    ("model/gltf-binary", "glb"), ("model/gltf+json", "gltf"), ("model/*", "glb"),
    ("application/json;q=0.5, model/gltf-binary", "glb"),
    ("model/gltf-binary;q=0.2, model/gltf+json;q=0.9", "gltf"),
    ("text/html, */*;q=0.1", "json"), ("application/*", "json"),
    ("model/gltf-binary;q=0, */*", "json"),
])
def test_negotiate(accept, expected):
    assert negotiate(accept) == expected


@pytest.mark.parametrize("accept", ["text/html", "application/json;q=0, model/*;q=0",
                                    "image/png"])
def test_negotiate_refuses(accept):
    with pytest.raises(ProblemError) as info:
        negotiate(accept)
    assert info.value.status == 406


def test_large_json_is_gzipped(client):
    V, F = icosphere(4)
    body = forms_json(V, F)
    response = client.post("/v1/reconstruct", json=body, headers={"accept-encoding": "gzip"})
    assert response.status_code == 200
    assert response.headers["content-encoding"] == "gzip"
    assert len(response.json()["vertices"]) == len(V)  # httpx decodes transparently
    raw = client.post("/v1/reconstruct", json=body, headers={"accept-encoding": "identity"})
    assert "content-encoding" not in raw.headers
    assert int(raw.headers["content-length"]) > 64 * 1024
    small = client.post("/v1/forms", json=mesh_json(*icosphere(0)),
                        headers={"accept-encoding": "gzip"})
    assert "content-encoding" not in small.headers
    assert gzip.compress(raw.content)  # sanity: the raw body is the uncompressed JSON
