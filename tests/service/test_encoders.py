"""glTF encoders: checked with the real Khronos glTF-Validator and round-tripped via trimesh."""

from __future__ import annotations

import base64
import io
import json
import struct
from typing import Any

import numpy as np
import pytest
import trimesh

from service.worker.output import MEDIA_TYPES
from solver.core.errors import IndexOutOfRangeError, NonFiniteValueError, ShapeMismatchError
from solver.mesh.gltf import (
    color_ramp,
    encode_gltf,
    encode_gltf_binary,
    encode_gltf_json,
    vertex_normals,
)
from tests.helpers.gltf_validator import ensure_validator_installed, issue_codes, validate_gltf
from tests.helpers.meshes import icosphere


@pytest.fixture(scope="module", autouse=True)
def _validator() -> None:
    ensure_validator_installed()


@pytest.fixture(scope="module")
def sphere() -> tuple[np.ndarray, np.ndarray]:
    return icosphere(2)


def _encode(kind: str, *args: Any, **kwargs: Any) -> bytes:
    return encode_gltf_binary(*args, **kwargs) if kind == "glb" else encode_gltf_json(
        *args, **kwargs)


def _validate(data: bytes, kind: str) -> dict[str, Any]:
    report = validate_gltf(data, kind)
    issues = report["issues"]
    print(f"validator {report['validatorVersion']} ({kind}): "
          f"{issues['numErrors']} errors, {issues['numWarnings']} warnings, "
          f"{issues['numInfos']} infos, {issues['numHints']} hints")
    for msg in issues["messages"]:
        print(f"  [{msg['severity']}] {msg['code']} {msg.get('pointer', msg.get('offset'))}: "
              f"{msg['message']}")
    return report


def _gltf_json(data: bytes, kind: str) -> tuple[dict[str, Any], bytes]:
    """(JSON document, binary buffer) of an encoded asset."""
    if kind == "gltf":
        doc = json.loads(data)
        uri = doc["buffers"][0]["uri"]
        prefix = "data:application/octet-stream;base64,"
        assert uri.startswith(prefix)
        return doc, base64.b64decode(uri[len(prefix):])
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A
    doc = json.loads(data[20:20 + json_len])
    bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
    assert bin_type == 0x004E4942
    return doc, data[28 + json_len:28 + json_len + bin_len]


# ------------------------------------------------------------------ real validator


@pytest.mark.parametrize("kind", ["glb", "gltf"])
@pytest.mark.parametrize("with_colors", [False, True], ids=["plain", "colors"])
def test_icosphere_validates_clean(sphere: tuple[np.ndarray, np.ndarray], kind: str,
                                   with_colors: bool) -> None:
    v, f = sphere
    colors = color_ramp(v[:, 2]) if with_colors else None
    report = _validate(_encode(kind, v, f, colors), kind)
    assert report["issues"]["numErrors"] == 0
    assert report["issues"]["numWarnings"] == 0
    assert report["mimeType"] == MEDIA_TYPES[kind]
    info = report["info"]
    assert info["version"] == "2.0"
    assert info["totalVertexCount"] == len(v)
    assert info["totalTriangleCount"] == len(f)
    assert info["materialCount"] == 1
    assert info["maxAttributes"] == (3 if with_colors else 2)


@pytest.mark.parametrize("kind", ["glb", "gltf"])
def test_unreferenced_vertex_validates(sphere: tuple[np.ndarray, np.ndarray], kind: str) -> None:
    """A vertex no face uses is legal glTF: the validator reports nothing for it (checked:
    no error, warning, info or hint), and it keeps its index and gets normal (0, 0, 1)."""
    v, f = sphere
    v2 = np.vstack([v[:10], [[3.0, 4.0, 5.0]], v[10:]])
    f2 = np.where(f >= 10, f + 1, f)
    data = _encode(kind, v2, f2, color_ramp(v2[:, 0]))
    report = _validate(data, kind)
    assert report["issues"]["numErrors"] == 0
    assert report["issues"]["numWarnings"] == 0
    assert report["info"]["totalVertexCount"] == len(v2)
    doc, binary = _gltf_json(data, kind)
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["NORMAL"]]
    view = doc["bufferViews"][acc["bufferView"]]
    normals = np.frombuffer(binary, "<f4", acc["count"] * 3, view["byteOffset"]).reshape(-1, 3)
    np.testing.assert_array_equal(normals[10], [0.0, 0.0, 1.0])


def test_degenerate_face_still_valid() -> None:
    """Zero-area faces are reported by the validator as infos only; normals stay unit."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 2]], dtype=float)
    f = np.array([[0, 1, 2], [3, 3, 3]])
    report = _validate(encode_gltf_binary(v, f), "glb")
    assert report["issues"]["numErrors"] == 0
    assert report["issues"]["numWarnings"] == 0
    assert set(issue_codes(report)) <= {"ACCESSOR_INDEX_TRIANGLE_DEGENERATE"}


def test_large_mesh_uses_uint32_indices_and_validates() -> None:
    nx, ny = 300, 220  # 66000 vertices > 65535
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.sin(x.ravel() / 7.0) * np.cos(y.ravel() / 5.0)],
                 axis=1)
    i = (np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + ny, i + 1], 1), np.stack([i + 1, i + ny, i + ny + 1], 1)])
    data = encode_gltf_binary(v, f, color_ramp(v[:, 2]))
    doc, _ = _gltf_json(data, "glb")
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] == 5125
    report = _validate(data, "glb")
    assert report["issues"]["numErrors"] == 0
    assert report["issues"]["numWarnings"] == 0


def test_small_mesh_uses_uint16_indices(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    doc, _ = _gltf_json(encode_gltf_binary(*sphere), "glb")
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] == 5123


def test_no_faces_is_a_valid_point_primitive() -> None:
    v = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    data = encode_gltf_binary(v, np.zeros((0, 3), dtype=np.int64))
    report = _validate(data, "glb")
    assert report["issues"]["numErrors"] == 0
    doc, _ = _gltf_json(data, "glb")
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0 and "indices" not in prim


# ------------------------------------------------------------------ structure


@pytest.mark.parametrize("kind", ["glb", "gltf"])
def test_document_structure(sphere: tuple[np.ndarray, np.ndarray], kind: str) -> None:
    v, f = sphere
    data = _encode(kind, v, f, color_ramp(v[:, 1]))
    doc, binary = _gltf_json(data, kind)
    assert doc["asset"]["version"] == "2.0"
    assert doc["asset"]["generator"]
    assert doc["scenes"][doc["scene"]]["nodes"] == [0]
    assert doc["nodes"][0]["mesh"] == 0
    (prim,) = doc["meshes"][0]["primitives"]
    assert prim["mode"] == 4
    assert set(prim["attributes"]) == {"POSITION", "NORMAL", "COLOR_0"}
    mat = doc["materials"][prim["material"]]
    assert mat["doubleSided"] is True and "pbrMetallicRoughness" in mat
    assert doc["buffers"][0]["byteLength"] == len(binary)
    for view in doc["bufferViews"]:
        assert view["byteOffset"] % 4 == 0
        assert view["byteOffset"] + view["byteLength"] <= len(binary)
    targets = {doc["accessors"][a]["bufferView"]: 34962 for a in prim["attributes"].values()}
    targets[doc["accessors"][prim["indices"]]["bufferView"]] = 34963
    for view_index, target in targets.items():
        assert doc["bufferViews"][view_index]["target"] == target
    pos = doc["accessors"][prim["attributes"]["POSITION"]]
    v32 = v.astype(np.float32)
    assert pos["min"] == v32.min(axis=0).tolist()
    assert pos["max"] == v32.max(axis=0).tolist()
    assert doc["accessors"][prim["attributes"]["COLOR_0"]]["type"] == "VEC4"


def test_glb_container_padding(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    data = encode_gltf_binary(*sphere)
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_len, _ = struct.unpack_from("<II", data, 12)
    assert json_len % 4 == 0
    chunk = data[20:20 + json_len]
    assert chunk.rstrip(b" ").endswith(b"}")  # padded with spaces
    bin_len, _ = struct.unpack_from("<II", data, 20 + json_len)
    assert bin_len % 4 == 0
    assert 28 + json_len + bin_len == len(data)


def test_without_normals(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    data = encode_gltf_binary(*sphere, normals=False)
    doc, _ = _gltf_json(data, "glb")
    assert set(doc["meshes"][0]["primitives"][0]["attributes"]) == {"POSITION"}
    assert _validate(data, "glb")["issues"]["numErrors"] == 0


def test_encode_gltf_dispatch(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    assert encode_gltf(*sphere, kind="glb") == encode_gltf_binary(*sphere)
    assert encode_gltf(*sphere, kind="gltf") == encode_gltf_json(*sphere)
    with pytest.raises(ValueError):
        encode_gltf(*sphere, kind="obj")  # type: ignore[arg-type]


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("kind", ["glb", "gltf"])
def test_trimesh_round_trip(sphere: tuple[np.ndarray, np.ndarray], kind: str) -> None:
    v, f = sphere
    rng = np.random.default_rng(1)
    perm = rng.permutation(len(v))  # non-trivial vertex order
    v = v[perm]
    f = np.argsort(perm)[f]
    colors = color_ramp(v[:, 0])
    scene = trimesh.load(io.BytesIO(_encode(kind, v, f, colors)), file_type=kind, process=False)
    (mesh,) = scene.geometry.values()
    np.testing.assert_array_equal(mesh.vertices, v.astype(np.float32))
    np.testing.assert_array_equal(mesh.faces, f)
    # With a material present trimesh keeps COLOR_0 as a float vertex attribute.
    np.testing.assert_array_equal(mesh.visual.vertex_attributes["color"], colors)


def test_solver_io_round_trip(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    from solver.mesh.io import load_mesh

    v, f = sphere
    v2, f2 = load_mesh(encode_gltf_binary(v, f), "glb")
    np.testing.assert_array_equal(v2, v.astype(np.float32))
    np.testing.assert_array_equal(f2, f)


# ------------------------------------------------------------------ normals, colours, errors


def test_vertex_normals_unit_and_outward(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = sphere
    n = vertex_normals(v, f)
    assert n.dtype == np.float32 and n.shape == v.shape
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    radial = v / np.linalg.norm(v, axis=1, keepdims=True)
    assert np.min(np.sum(n * radial, axis=1)) > 0.99


def test_vertex_normals_area_weighted() -> None:
    # Vertex 0 is shared by a big face in the xy-plane and a small one in the xz-plane.
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, -1], [1, 0, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 3, 4]])
    n0 = vertex_normals(v, f)[0].astype(float)
    expected = np.array([0.0, -1.0, 100.0])  # cross products: (0,0,100) and (0,-1,0)
    np.testing.assert_allclose(n0, expected / np.linalg.norm(expected), rtol=1e-6)


def test_color_ramp() -> None:
    vals = np.array([0.0, 0.5, 1.0, np.nan, 2.0, -1.0, np.inf])
    c = color_ramp(vals, 0.0, 1.0, linear=False)
    assert c.dtype == np.float32 and c.shape == (7, 4)
    np.testing.assert_allclose(c[0, :3], [0.267004, 0.004874, 0.329415], atol=1e-6)  # viridis 0
    np.testing.assert_allclose(c[2, :3], [0.993248, 0.906157, 0.143936], atol=1e-6)  # viridis 1
    np.testing.assert_array_equal(c[3], [0.5, 0.5, 0.5, 1.0])  # NaN -> grey
    np.testing.assert_array_equal(c[4], c[2])  # clamped
    np.testing.assert_array_equal(c[5], c[0])
    np.testing.assert_array_equal(c[6], c[2])
    assert np.all(c[:, 3] == 1.0)
    lin = color_ramp(vals, 0.0, 1.0)
    assert np.all((lin >= 0) & (lin <= 1))
    assert np.all(lin[[0, 1, 2], :3] <= c[[0, 1, 2], :3] + 1e-7)  # linear <= sRGB in [0, 1]
    # default range = finite min/max; luminance increases along the ramp
    ramp = color_ramp(np.linspace(-3.0, 7.0, 50), linear=False)
    np.testing.assert_array_equal(ramp[0], c[0])
    lum = ramp[:, :3] @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(lum) > 0)
    # degenerate inputs
    assert np.all(np.isfinite(color_ramp(np.full(4, 3.0))))
    np.testing.assert_array_equal(color_ramp(np.full(3, np.nan)), np.tile(c[3], (3, 1)))
    assert color_ramp(np.zeros(0)).shape == (0, 4)


def test_media_types() -> None:
    assert MEDIA_TYPES == {"json": "application/json", "glb": "model/gltf-binary",
                           "gltf": "model/gltf+json", "f32": "application/octet-stream"}


def test_input_errors(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = sphere
    with pytest.raises(ShapeMismatchError):
        encode_gltf_binary(v[:, :2], f)
    with pytest.raises(ShapeMismatchError):
        encode_gltf_binary(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(ShapeMismatchError):
        encode_gltf_binary(v, f, colors=np.ones((len(v) - 1, 4)))
    with pytest.raises(IndexOutOfRangeError):
        encode_gltf_binary(v, np.vstack([f, [[0, 1, len(v)]]]))
    bad = v.copy()
    bad[5, 1] = np.nan
    with pytest.raises(NonFiniteValueError):
        encode_gltf_json(bad, f)
    with pytest.raises(NonFiniteValueError):
        encode_gltf_binary(v * 1e300, f)  # overflows float32


@pytest.mark.parametrize("kind", ["glb", "gltf"])
def test_the_librarys_files_are_the_same_writer_and_validator_clean(
        kind: str, sphere: tuple[np.ndarray, np.ndarray]) -> None:
    """solver.mesh.io.save_mesh and solver.mesh.uv_files.textured_glb write through this one writer:
    the same bytes as encode_gltf, no validator error or warning."""
    from solver.mesh.io import save_mesh
    from solver.mesh.uv_files import textured_glb

    v, f = sphere
    data = save_mesh(v, f, kind)
    assert data == encode_gltf(v, f, kind=kind)
    assert issue_codes(_validate(data, kind), max_severity=1) == []
    if kind == "glb":  # an atlas: one vertex per uv index, TEXCOORD_0
        uv = (v[:, :2] - v[:, :2].min(axis=0)) / np.ptp(v[:, :2], axis=0).max()
        textured = textured_glb(v, uv, f, np.arange(len(v)))
        assert textured == encode_gltf(v, f, kind="glb", texcoords=uv)
        doc, _ = _gltf_json(textured, "glb")
        assert "TEXCOORD_0" in doc["meshes"][0]["primitives"][0]["attributes"]
        assert issue_codes(_validate(textured, "glb"), max_severity=1) == []
