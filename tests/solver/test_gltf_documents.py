"""Files as other tools write them (assimp's test models): a ``.gltf`` whose buffers are files
beside it (read from disk with them; as bytes alone refused in words that say what to send),
Draco-compressed glTF refused instead of read as zeros, and text files (OBJ, OFF, glTF,
ASCII STL) in UTF-16 or with UTF-8's byte-order mark read as their UTF-8 selves.
"""

from __future__ import annotations

import base64
import codecs
import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest

from solver.core.errors import MeshFileError
from solver.mesh.gltf import encode_gltf_json
from solver.mesh.io import load_mesh_file, read_mesh, save_mesh
from tests.helpers import DATA
from tests.helpers.meshes import icosphere, torus_grid


def _separate(V: np.ndarray, F: np.ndarray, folder: Path, name: str = "part 1.bin",
              image: bool = False) -> Path:
    """Our own .gltf of (V, F) with its buffer moved to the file ``name`` beside it."""
    doc = json.loads(encode_gltf_json(V, F))
    payload = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    (folder / name).write_bytes(payload)
    doc["buffers"][0]["uri"] = name.replace(" ", "%20")  # a URI: spaces escaped
    if image:
        doc["images"] = [{"uri": "texture that is not there.png"}]
    path = folder / "model.gltf"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("mesh", [icosphere(2), torus_grid(10, 6)], ids=["sphere", "torus"])
@pytest.mark.parametrize("image", [False, True], ids=["", "with an image file"])
def test_a_gltf_beside_its_buffer_reads_from_disk_as_the_embedded_one(tmp_path, mesh, image):
    V, F = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1])
    embedded = read_mesh(encode_gltf_json(V, F), "gltf")
    path = _separate(V, F, tmp_path, image=image)
    vertices, faces = load_mesh_file(path)
    np.testing.assert_array_equal(vertices, embedded.vertices)
    np.testing.assert_array_equal(faces, embedded.faces)
    np.testing.assert_allclose(vertices, V, atol=1e-6)


def test_a_gltf_sent_without_its_buffer_says_what_to_send(tmp_path):
    V, F = icosphere(1)
    path = _separate(np.asarray(V, float), np.asarray(F), tmp_path)
    with pytest.raises(MeshFileError, match=re.escape(
            "buffer 0 is the separate file 'part%201.bin': send the model as GLB")):
        read_mesh(path.read_bytes(), "model.gltf")
    (tmp_path / "part 1.bin").unlink()
    missing = re.escape("buffer 0: cannot read its file 'part%201.bin'")
    with pytest.raises(MeshFileError, match=missing):
        load_mesh_file(path)


@pytest.mark.skipif(importlib.util.find_spec("DracoPy") is not None,
                    reason="DracoPy decodes Draco here")
@pytest.mark.parametrize("kind", ["gltf", "glb"])
def test_draco_compressed_meshes_are_refused_not_read_as_zeros(kind):
    V, F = icosphere(1)
    doc = json.loads(encode_gltf_json(np.asarray(V, float), np.asarray(F)))
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["KHR_draco_mesh_compression"]
    text = json.dumps(doc).encode()
    if kind == "glb":
        text += b" " * (-len(text) % 4)
        data = (b"glTF" + (2).to_bytes(4, "little") + (20 + len(text)).to_bytes(4, "little")
                + len(text).to_bytes(4, "little") + b"JSON" + text)
    else:
        data = text
    with pytest.raises(MeshFileError, match="Draco-compressed"):
        read_mesh(data, kind)


def _encodings(text: bytes) -> dict[str, bytes]:
    return {"utf-16-le": codecs.BOM_UTF16_LE + text.decode().encode("utf-16-le"),
            "utf-16-be": codecs.BOM_UTF16_BE + text.decode().encode("utf-16-be"),
            "utf-8 with a mark": codecs.BOM_UTF8 + text}


def _ascii_stl(V: np.ndarray, F: np.ndarray) -> bytes:
    rows = "".join("facet normal 0 0 0\nouter loop\n" + "".join(
        f"vertex {x!r} {y!r} {z!r}\n" for x, y, z in V[f].tolist()) + "endloop\nendfacet\n"
        for f in np.asarray(F))
    return ("solid grid\n" + rows + "endsolid grid\n").encode()


def _plain(fmt: str, V: np.ndarray, F: np.ndarray) -> bytes:
    if fmt == "gltf":
        return encode_gltf_json(V, F)
    return _ascii_stl(V, F) if fmt == "stl" else save_mesh(V, F, fmt)


@pytest.mark.parametrize("fmt", ["obj", "off", "gltf", "stl"])
@pytest.mark.parametrize("encoding", ["utf-16-le", "utf-16-be", "utf-8 with a mark"])
def test_text_files_with_a_byte_order_mark_read_as_their_utf8_selves(fmt, encoding):
    V, F = torus_grid(8, 5)
    plain = _plain(fmt, np.asarray(V, dtype=np.float64), np.asarray(F))
    expected = read_mesh(plain, fmt)
    loaded = read_mesh(_encodings(plain)[encoding], fmt)
    np.testing.assert_array_equal(loaded.vertices, expected.vertices)
    np.testing.assert_array_equal(loaded.faces, expected.faces)


def test_assimps_utf16_big_endian_box_is_a_cube():
    loaded = read_mesh((DATA / "assimp_box_UTF16BE.obj").read_bytes(), "obj")
    assert loaded.vertices.shape == (8, 3) and loaded.faces.shape == (12, 3)
    assert loaded.polygons == 6
    extent = loaded.vertices.max(axis=0) - loaded.vertices.min(axis=0)
    np.testing.assert_allclose(extent, extent[0])  # a cube


def test_an_ascii_stl_after_blank_lines_and_a_binary_one_with_a_marked_header():
    V, F = torus_grid(8, 5)
    V = np.asarray(V, dtype=np.float64)
    text = _ascii_stl(V, F)
    expected = read_mesh(text, "stl")
    np.testing.assert_array_equal(read_mesh(b"\n  \n" + text, "stl").faces, expected.faces)
    binary = bytearray(save_mesh(V, F, "stl"))
    binary[:3] = codecs.BOM_UTF8  # a header that starts like marked text stays binary
    loaded = read_mesh(bytes(binary), "stl")
    np.testing.assert_array_equal(loaded.faces, read_mesh(save_mesh(V, F, "stl"), "stl").faces)
