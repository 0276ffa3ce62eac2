"""Multipart array fields come as one JSON part or as one part per item (how generated
clients send them) with the same answer; ``?format=`` chooses the result like ``Accept``."""

from __future__ import annotations

import json

import numpy as np

from tests.helpers import REPO
from tests.helpers.meshes import grid

FACE = (REPO / "tests" / "data" / "face.off").read_bytes()
HANDLES = [{"vertex": 0, "position": [0.0, 0.0, 0.0]},
           {"vertex": 10, "position": [0.1, 0.2, 0.3]},
           {"vertex": 40, "position": [0.0, 0.1, 0.0]}]


def _deform(client, fields, mesh=FACE):
    response = client.post("/v1/deform", files=[("file", ("mesh.off", mesh)), *fields])
    assert response.status_code == 200, response.text
    return np.asarray(response.json()["vertices"])


def test_deform_handles_as_one_part_or_one_part_per_item(client):
    one = _deform(client, [("handles", (None, json.dumps(HANDLES)))])
    per_item = _deform(client, [("handles", (None, json.dumps(h), "application/json"))
                                for h in HANDLES])
    np.testing.assert_array_equal(one, per_item)
    for handle in HANDLES:
        np.testing.assert_allclose(per_item[handle["vertex"]], handle["position"], atol=1e-6)
    single = _deform(client, [("handles", (None, json.dumps(HANDLES[1])))])
    np.testing.assert_allclose(single[10], HANDLES[1]["position"], atol=1e-6)
    V, F = grid(6, 6)  # 49 vertices: one part each stays within the form's 64 parts
    off = "OFF\n{} {} 0\n{}\n{}\n".format(
        len(V), len(F), "\n".join(" ".join(map(repr, v)) for v in V.tolist()),
        "\n".join("3 " + " ".join(map(str, f)) for f in F.tolist())).encode()
    handles = [{"vertex": 0, "position": [0.0, 0.0, 0.2]},
               {"vertex": 35, "position": [1.0, 1.0, 0.0]}]
    roi = [v for v in range(len(V)) if v != 7]
    answers = [
        _deform(client, [("handles", (None, json.dumps(handles))),
                         ("roi", (None, json.dumps(roi)))], off),
        _deform(client, [*(("handles", (None, json.dumps(h))) for h in handles),
                         *(("roi", (None, str(v))) for v in roi)], off)]
    np.testing.assert_array_equal(*answers)
    np.testing.assert_array_equal(answers[0][7], V[7])  # outside the region: kept


def test_interpolate_t_as_repeated_parts(client):
    files = [("file_a", ("a.off", FACE)), ("file_b", ("b.off", FACE))]
    parts = client.post("/v1/interpolate", files=[*files, ("t", (None, "0")), ("t", (None, "1"))])
    assert parts.status_code == 200, parts.text
    assert parts.json()["t"] == [0.0, 1.0] and len(parts.json()["vertices"]) == 2
    one = client.post("/v1/interpolate", files=[*files, ("t", (None, "0.5"))])
    assert one.json()["t"] == 0.5


def test_a_scalar_field_given_twice_is_a_validation_error(client):
    response = client.post("/v1/integrability", files=[
        ("file", ("face.off", FACE)), ("tolerance", (None, "1e-6")),
        ("tolerance", (None, "1e-7"))])
    assert response.status_code == 422
    assert response.json()["errors"][0]["field"] == "tolerance"


def test_format_query_overrides_accept(client):
    body = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}
    glb = client.post("/v1/mesh?format=glb", json=body, headers={"Accept": "application/json"})
    assert glb.headers["content-type"] == "model/gltf-binary" and glb.content[:4] == b"glTF"
    gltf = client.post("/v1/mesh?format=gltf", json=body)
    assert gltf.json()["asset"]["version"] == "2.0"
    assert client.post("/v1/mesh?format=json", json=body,
                       headers={"Accept": "model/gltf-binary"}).json()["faces"] == [[0, 1, 2]]
    refused = client.post("/v1/forms?format=glb", json=body)
    assert refused.status_code == 406 and refused.json()["kind"] == "not-acceptable"
    assert client.post("/v1/mesh?format=obj", json=body).status_code == 422
