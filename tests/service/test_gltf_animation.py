"""Animated glTF of a blend sequence (solver.mesh.gltf.encode_gltf_animation): validated
by the Khronos validator, and its morph targets and keyframes read back from the bytes."""

from __future__ import annotations

import base64
import json
import struct

import numpy as np
import pytest

from solver import blend
from solver.core.errors import SolverInputError
from solver.mesh.gltf import encode_gltf_animation
from tests.helpers.gltf_validator import issue_codes, validate_gltf
from tests.helpers.meshes import load
from tests.helpers.poses import bent_pose


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """The JSON document and BIN chunk of a GLB."""
    magic, version, total = struct.unpack_from("<III", data, 0)
    assert (magic, version, total) == (0x46546C67, 2, len(data))
    js_len, _ = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20:20 + js_len])
    bin_len, _ = struct.unpack_from("<II", data, 20 + js_len)
    return doc, data[28 + js_len:28 + js_len + bin_len]


def accessor(doc: dict, binary: bytes, index: int) -> np.ndarray:
    a = doc["accessors"][index]
    view = doc["bufferViews"][a["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3}[a["type"]]
    raw = np.frombuffer(binary, dtype="<f4", count=a["count"] * width,
                        offset=view["byteOffset"])
    return raw.reshape(a["count"], width) if width > 1 else raw


@pytest.fixture(scope="module")
def sequence():
    V, F = load("decimated-knight.off")
    P = bent_pose(V, F, 0.6)
    t = np.linspace(0.0, 1.5, 7)
    return blend([V, P], np.stack([1 - t, t], axis=1), F), V, F


@pytest.mark.parametrize("kind", ["glb", "gltf"])
def test_animated_blend_validates_clean(sequence, kind):
    out, V, F = sequence
    data = encode_gltf_animation(out.vertices, F, base=V, kind=kind)
    report = validate_gltf(data, kind)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, \
        issue_codes(report)
    assert report["info"]["animationCount"] == 1
    assert report["info"]["totalVertexCount"] == len(V)


def test_morph_targets_and_keyframes_read_back(sequence):
    out, V, F = sequence
    times = np.linspace(0.0, 3.0, len(out.vertices))
    doc, binary = read_glb(encode_gltf_animation(out.vertices, F, base=V, times=times))
    primitive = doc["meshes"][0]["primitives"][0]
    base = accessor(doc, binary, primitive["attributes"]["POSITION"])
    assert np.abs(base - V).max() < 1e-6 * np.ptp(V)
    for k, target in enumerate(primitive["targets"]):
        shape = base + accessor(doc, binary, target["POSITION"])
        assert np.abs(shape - out.vertices[k]).max() < 1e-5 * np.ptp(V)
    sampler = doc["animations"][0]["samplers"][0]
    assert np.allclose(accessor(doc, binary, sampler["input"]), times)
    weights = accessor(doc, binary, sampler["output"]).reshape(len(times), len(times))
    assert np.array_equal(weights, np.eye(len(times)))
    assert doc["animations"][0]["channels"][0]["target"] == {"node": 0, "path": "weights"}


def test_gltf_embeds_the_same_buffer(sequence):
    out, _, F = sequence
    doc = json.loads(encode_gltf_animation(out.vertices, F, kind="gltf"))
    glb_doc, binary = read_glb(encode_gltf_animation(out.vertices, F))
    uri = doc["buffers"][0]["uri"]
    assert base64.b64decode(uri.split(",", 1)[1]) == binary[:glb_doc["buffers"][0]["byteLength"]]


@pytest.mark.parametrize("change, field", [
    ({"times": [0.0, 0.0]}, "times"), ({"base": np.zeros((3, 3))}, "base"),
    ({"rows": np.zeros((0, 4, 3))}, "rows"), ({"rows": np.full((2, 4, 3), np.nan)}, "rows"),
])
def test_bad_sequences_are_refused(change, field):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    arguments = {"rows": np.stack([V, 2 * V]), "faces": [[0, 2, 1], [0, 1, 3]], **change}
    with pytest.raises(SolverInputError) as error:
        encode_gltf_animation(**arguments)
    assert getattr(error.value, "field", None) == field
