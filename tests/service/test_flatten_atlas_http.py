"""Flatten anything over HTTP (issue 41): a closed genus-0 mesh, a genus-2 surface and a
multi-part model, sync and as a job, JSON arrays checked independently and GLB with
TEXCOORD_0 valid for the Khronos validator."""

from __future__ import annotations

import json
import struct
import time

import numpy as np
import pytest

from tests.helpers.atlas import genus_two, overlapping_pixels
from tests.helpers.gltf_validator import validate_gltf
from tests.helpers.meshes import holed, icosphere, load, side_by_side
from tests.helpers.service import mesh_json

CASES = {
    "knight (closed genus 0)": lambda: load("decimated-knight.off"),
    "slab (genus 2)": genus_two,
    "multi-part": lambda: side_by_side(icosphere(2), load("torus.off")),
    "face scan with holes": lambda: holed(*load("face.off"), [300, 600, 900]),
}


def _check(V, F, doc):
    texcoords = np.asarray(doc["texcoords"])
    uv_faces = np.asarray(doc["uv_faces"])
    uv_vertex = np.asarray(doc["uv_vertex"])
    face_chart = np.asarray(doc["face_chart"])
    assert np.array_equal(uv_vertex[uv_faces], F)
    assert doc["report"]["atlas"]["charts"] == face_chart.max() + 1
    assert doc["flipped_faces"] == [] and doc["report"]["flipped_count"] == 0
    e1 = texcoords[uv_faces[:, 1]] - texcoords[uv_faces[:, 0]]
    e2 = texcoords[uv_faces[:, 2]] - texcoords[uv_faces[:, 0]]
    assert (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0).all()
    assert overlapping_pixels(texcoords, uv_faces, face_chart) == 0
    return texcoords, uv_faces, uv_vertex


def _glb_accessor(data: bytes, name: str) -> np.ndarray:
    """The float32 attribute ``name`` of a GLB's first primitive, read from its bytes."""
    length, _ = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20:20 + length])
    accessor = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][name]]
    view = doc["bufferViews"][accessor["bufferView"]]
    start = 20 + length + 8 + view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    width = {"VEC2": 2, "VEC3": 3}[accessor["type"]]
    return np.frombuffer(data, np.float32, accessor["count"] * width, start).reshape(-1, width)


def _glb_attributes(data: bytes) -> dict:
    length, _ = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20:20 + length])
    return doc["meshes"][0]["primitives"][0]["attributes"]


@pytest.mark.parametrize("name", list(CASES))
def test_sync_flatten_gives_an_atlas_and_a_textured_glb(client, name):
    V, F = CASES[name]()
    response = client.post("/v1/parameterize", json=mesh_json(V, F))
    assert response.status_code == 200, response.text
    texcoords, _, uv_vertex = _check(V, F, response.json())
    glb = client.post("/v1/parameterize", json=mesh_json(V, F),
                      headers={"accept": "model/gltf-binary"})
    assert glb.status_code == 200, glb.text
    report = validate_gltf(glb.content, "glb")
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    assert report["info"]["totalVertexCount"] == len(uv_vertex)
    assert "TEXCOORD_0" in _glb_attributes(glb.content)
    # TEXCOORD_0 is the atlas with glTF's v down; POSITION the file's vertices per uv index.
    np.testing.assert_allclose(_glb_accessor(glb.content, "TEXCOORD_0"),
                               np.column_stack([texcoords[:, 0], 1 - texcoords[:, 1]]),
                               atol=1e-6)
    np.testing.assert_allclose(_glb_accessor(glb.content, "POSITION"), V[uv_vertex],
                               atol=1e-5 * np.abs(V).max())


def test_flatten_job_reports_progress_per_chart(client):
    V, F = load("decimated-knight.off")
    response = client.post("/v1/jobs", json={"operation": "parameterize",
                                             "input": mesh_json(V, F)})
    assert response.status_code == 202, response.text
    location = response.headers["location"]
    assert "charts" in response.json()["progress"]["stages"]
    fractions = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        doc = client.get(location).json()
        if doc["progress"]["stage"] == "charts":
            fractions.append(doc["progress"]["stages"]["charts"])
        if doc["status"] in ("succeeded", "failed"):
            break
        time.sleep(0.05)
    assert doc["status"] == "succeeded", doc
    assert fractions == sorted(fractions) and any(0 < f < 1 for f in fractions)
    result = client.get(f"{location}/result", headers={"accept": "application/json"})
    _check(V, F, result.json())
    glb = client.get(f"{location}/result", headers={"accept": "model/gltf-binary"})
    assert glb.status_code == 200 and "TEXCOORD_0" in _glb_attributes(glb.content)
