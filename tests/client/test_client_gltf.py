"""A ``.gltf`` whose buffers are files beside it, sent by the client (``load_mesh``,
``blend_files``) to a real uvicorn: the client embeds them (the service gets bytes alone and
would answer 400 naming the buffer file), by the rule the library applies to files on disk
(:mod:`ffs_wire.gltf`, :func:`solver.mesh.gltf_documents.embed_buffers`): both give the
same bytes."""

from __future__ import annotations

import base64
import codecs
import json
from pathlib import Path

import numpy as np
import pytest

import ffs
from ffs_wire import gltf as wire_gltf
from solver.mesh import io as mesh_io
from solver.mesh.gltf import encode_gltf_json
from tests.helpers.meshes import torus_grid


def _beside(V: np.ndarray, F: np.ndarray, folder: Path, stem: str, *,
            image: bool = False, utf16: bool = False) -> Path:
    """``stem.gltf`` of (V, F) with its buffer in the file ``stem part.bin`` beside it (the
    URI escapes the space), optionally naming an image file that is not there, optionally
    in UTF-16 with a byte-order mark."""
    doc = json.loads(encode_gltf_json(V, F))
    name = f"{stem} part.bin"
    (folder / name).write_bytes(base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1]))
    doc["buffers"][0]["uri"] = name.replace(" ", "%20")
    if image:
        doc["images"] = [{"uri": "texture that is not there.png"}]
    path = folder / f"{stem}.gltf"
    text = json.dumps(doc, indent=1)
    path.write_bytes(codecs.BOM_UTF16_LE + text.encode("utf-16-le") if utf16
                     else text.encode())
    return path


def _torus() -> tuple[np.ndarray, np.ndarray]:
    V, F = torus_grid(12, 8)
    return np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)


@pytest.mark.parametrize("utf16", [False, True], ids=["utf-8", "utf-16"])
def test_load_mesh_sends_a_gltf_with_the_buffer_beside_it(server, tmp_path, utf16):
    V, F = _torus()
    path = _beside(V, F, tmp_path, "torus", image=True, utf16=utf16)
    with ffs.Client(server) as client:
        mesh = client.load_mesh(path)
    local_vertices, local_faces = mesh_io.load_mesh_file(path)  # the library, from disk
    np.testing.assert_array_equal(mesh.vertices, local_vertices)
    np.testing.assert_array_equal(mesh.faces, local_faces)
    np.testing.assert_array_equal(mesh.faces, F)
    np.testing.assert_allclose(mesh.vertices, V, atol=1e-6)  # float32 in the file


def test_blend_files_sends_gltf_shapes_with_their_buffers(server, tmp_path):
    V, F = _torus()
    bent = V * [1.0, 1.0, 1.5]
    a = _beside(V, F, tmp_path, "rest")
    b = _beside(bent, F, tmp_path, "tall")
    with ffs.Client(server) as client:
        blend = client.blend_files([a, b], t=[0.0, 1.0], refine=False)
    assert blend.vertices.shape == (2, len(V), 3)
    scale = np.ptp(V, axis=0).max()
    for row, shape in zip(blend.vertices, (V, bent), strict=True):  # ends: the shapes
        centred = row - row.mean(axis=0)
        np.testing.assert_allclose(np.ptp(centred, axis=0), np.ptp(shape, axis=0),
                                   atol=1e-4 * scale)


def test_a_missing_buffer_file_is_named_before_anything_is_sent(server, tmp_path):
    V, F = _torus()
    path = _beside(V, F, tmp_path, "torus")
    (tmp_path / "torus part.bin").unlink()
    with ffs.Client(server) as client, pytest.raises(ffs.LocalFileError) as caught:
        client.load_mesh(path)
    error = caught.value
    assert (error.field, error.index) == ("buffers", 0)
    assert str(error) == (f"{path}: buffers[0]: cannot read its file 'torus%20part.bin' beside "
                          "the document (No such file or directory)")


@pytest.mark.parametrize("case", ["separate buffer and image", "utf-16", "embedded",
                                  "not json"])
def test_the_client_and_the_library_embed_the_same_bytes(tmp_path, case):
    V, F = _torus()
    if case == "embedded":
        path = tmp_path / "embedded.gltf"
        path.write_bytes(encode_gltf_json(V, F))
    elif case == "not json":
        path = tmp_path / "broken.gltf"
        path.write_bytes(b'{"buffers": [')
    else:
        path = _beside(V, F, tmp_path, "torus", image=True, utf16=case == "utf-16")
    sent = wire_gltf.file_bytes(path)
    assert sent == mesh_io.file_bytes(path)
    if case != "not json":
        assert all(b["uri"].startswith("data:") for b in json.loads(sent)["buffers"])
        assert all("uri" not in image for image in json.loads(sent).get("images", []))


def test_khronos_primitive_modes_beside_its_buffer_reads_on_the_service(server, tmp_path):
    """Khronos' MeshPrimitiveModes as its glTF folder has it (``buffer.bin`` beside the
    document): uploaded by the client, read by the service with its triangle strip and fan
    (16 triangles of the list, strip and fan meshes; points and lines left out), as the
    library reads it from disk."""
    from tests.helpers import DATA

    doc = json.loads((DATA / "khronos_MeshPrimitiveModes.gltf").read_bytes())
    uri = doc["buffers"][0]["uri"]
    (tmp_path / "buffer.bin").write_bytes(base64.b64decode(uri.split(",", 1)[1]))
    doc["buffers"][0]["uri"] = "buffer.bin"
    path = tmp_path / "MeshPrimitiveModes.gltf"
    path.write_text(json.dumps(doc))
    with ffs.Client(server) as client:
        mesh = client.load_mesh(path)
    assert mesh.faces.shape == (16, 3) and mesh.vertices.shape == (21, 3)
    local_vertices, local_faces = mesh_io.load_mesh_file(path)
    np.testing.assert_array_equal(mesh.vertices, local_vertices)
    np.testing.assert_array_equal(mesh.faces, local_faces)
