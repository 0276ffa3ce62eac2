"""Files as other tools write them (assimp's test models): a ``.gltf`` whose buffers are files
beside it (read from disk with them; as bytes alone refused in words that say what to send),
Draco-compressed glTF refused instead of read as zeros, and text files (OBJ, OFF, glTF,
ASCII STL) in UTF-16 or with UTF-8's byte-order mark read as their UTF-8 selves; triangle
strips and fans (primitive modes 5 and 6, GLB and .gltf, indexed or not) read as the triangle
lists they draw, checked against the same meshes written as lists and against Khronos'
MeshPrimitiveModes sample.
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


# ------------------------------------------------------- triangle strips and fans (mode 5, 6)

def _gltf_file(positions: np.ndarray, primitives: list[tuple[np.ndarray | None, int]],
               kind: str, index_type: str = "<u2") -> bytes:
    """A glTF file of one mesh: float32 ``positions`` (one accessor) and one primitive per
    ``(indices or None, mode)``, its indices of ``index_type``; ``kind`` ``gltf`` (a data: URI
    buffer) or ``glb`` (the BIN chunk)."""
    component = {"<u1": 5121, "<u2": 5123, "<u4": 5125}[index_type]
    chunks = [np.asarray(positions, dtype="<f4").tobytes()]
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": len(chunks[0]), "target": 34962}]
    accessors = [{"bufferView": 0, "componentType": 5126, "count": len(positions),
                  "type": "VEC3", "min": np.min(positions, 0).tolist(),
                  "max": np.max(positions, 0).tolist()}]
    prims, offset = [], len(chunks[0])
    for indices, mode in primitives:
        prim: dict = {"attributes": {"POSITION": 0}, "mode": mode}
        if indices is not None:
            raw = np.asarray(indices, dtype=index_type).tobytes()
            raw += b"\0" * (-len(raw) % 4)
            views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw),
                          "target": 34963})
            accessors.append({"bufferView": len(views) - 1, "componentType": component,
                              "count": len(indices), "type": "SCALAR"})
            prim["indices"] = len(accessors) - 1
            chunks.append(raw)
            offset += len(raw)
        prims.append(prim)
    binary = b"".join(chunks)
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}], "meshes": [{"primitives": prims}],
           "accessors": accessors, "bufferViews": views,
           "buffers": [{"byteLength": len(binary)}]}
    if kind == "gltf":
        doc["buffers"][0]["uri"] = ("data:application/octet-stream;base64,"
                                    + base64.b64encode(binary).decode())
        return json.dumps(doc).encode()
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = (len(text).to_bytes(4, "little") + b"JSON" + text
            + len(binary).to_bytes(4, "little") + b"BIN\0" + binary)
    return b"glTF" + (2).to_bytes(4, "little") + (12 + len(body)).to_bytes(4, "little") + body


def _stitched(strips: list[np.ndarray]) -> np.ndarray:
    """The strips joined into one by repeating the last index of each and the first of the
    next (two triangles per join that repeat an index: not faces)."""
    joined = [strips[0]]
    for strip in strips[1:]:
        joined += [joined[-1][-1:], strip[:1], strip]
    return np.concatenate(joined)


def _corner_positions(loaded) -> set[tuple]:
    """Each triangle as the positions of its corners, rotated to start at the smallest
    (orientation kept): comparable across meshes whose vertices are numbered differently."""
    out = set()
    for corners in loaded.vertices[loaded.faces]:
        rows = [tuple(c) for c in corners.tolist()]
        k = rows.index(min(rows))
        out.add(tuple(rows[k:] + rows[:k]))
    return out


@pytest.mark.parametrize("kind", ["gltf", "glb"])
@pytest.mark.parametrize("index_type", ["<u1", "<u2", "<u4"])
def test_an_indexed_triangle_strip_reads_as_the_triangle_list_it_draws(kind, index_type):
    from tests.solver.test_strips import canonical, grid_strips

    vertices, strips, direct = grid_strips(4, 5)
    strip = _stitched(strips)  # one strip, the rows joined by repeated indices
    listed = read_mesh(_gltf_file(vertices, [(direct.ravel(), 4)], kind, index_type), kind)
    loaded = read_mesh(_gltf_file(vertices, [(strip, 5)], kind, index_type), kind)
    np.testing.assert_array_equal(loaded.vertices, listed.vertices)
    assert len(loaded.faces) == len(direct) == 40  # the joins' triangles are not faces
    assert canonical(loaded.faces) == canonical(listed.faces) == canonical(direct)
    v = loaded.vertices[loaded.faces]  # one orientation: every normal +z, as the list's
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (normals[:, 2] > 0).all()


@pytest.mark.parametrize("kind", ["gltf", "glb"])
def test_a_triangle_fan_reads_as_the_polygon_it_draws(kind):
    angles = np.linspace(0, 2 * np.pi, 9)[:-1]
    vertices = np.c_[np.cos(angles), np.sin(angles), 0.3 * np.cos(2 * angles)]
    vertices = np.vstack([[0.0, 0.0, 1.0], vertices])  # a cone-like cap around vertex 0
    fan = np.r_[0, 1 + np.arange(8), 1]
    ring = np.arange(1, 9)
    direct = np.c_[np.zeros(8, int), ring, np.roll(ring, -1)]
    listed = read_mesh(_gltf_file(vertices, [(direct.ravel(), 4)], kind), kind)
    loaded = read_mesh(_gltf_file(vertices, [(fan, 6)], kind), kind)
    np.testing.assert_array_equal(loaded.faces, listed.faces)  # same triangles, same order
    np.testing.assert_array_equal(loaded.faces, direct)
    # and as OFF reads the same octagon-with-apex: a fan of the polygon's corners
    off = read_mesh(b"OFF\n9 1 0\n" + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in
                    vertices.tolist()).encode() + b"10 " + " ".join(map(str, fan)).encode()
                    + b"\n", "off")
    np.testing.assert_array_equal(loaded.faces, off.faces)


@pytest.mark.parametrize("kind", ["gltf", "glb"])
def test_strips_and_fans_without_indices_draw_their_vertices_in_order(kind):
    from tests.solver.test_strips import grid_strips

    vertices, strips, direct = grid_strips(3, 4)
    # one strip primitive per row, vertices in strip order, no index accessor; and a fan
    rows = np.concatenate(strips)
    fan_vertices = np.array([[9.0, 9, 0], [10, 9, 0], [10, 10, 0], [9, 10, 0]])
    positions = np.vstack([vertices[rows], fan_vertices])
    listed = read_mesh(_gltf_file(vertices, [(direct.ravel(), 4)], kind), kind)
    first, prims = 0, []
    for strip in strips:  # each row its own primitive: a slice of the positions
        prims.append((first + np.arange(len(strip)), 5))
        first += len(strip)
    flat = read_mesh(_gltf_file(positions, prims, kind), kind)  # indexed, for comparison
    doc = json.loads(_gltf_file(positions, [], "gltf"))
    # the same primitives as accessors over slices of the positions, without indices
    views = doc["bufferViews"]
    meshes = []
    first = 0
    for count in [len(s) for s in strips] + [4]:
        views.append({"buffer": 0, "byteOffset": 12 * first, "byteLength": 12 * count,
                      "target": 34962})
        doc["accessors"].append({"bufferView": len(views) - 1, "componentType": 5126,
                                 "count": count, "type": "VEC3"})
        mode = 5 if first < len(rows) else 6
        meshes.append({"attributes": {"POSITION": len(doc["accessors"]) - 1}, "mode": mode})
        first += count
    doc["meshes"] = [{"primitives": meshes}]
    data = json.dumps(doc).encode()
    if kind == "glb":
        payload = base64.b64decode(doc["buffers"][0].pop("uri").split(",", 1)[1])
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        body = (len(text).to_bytes(4, "little") + b"JSON" + text
                + len(payload).to_bytes(4, "little") + b"BIN\0" + payload)
        data = b"glTF" + (2).to_bytes(4, "little") + (12 + len(body)).to_bytes(4, "little") + body
    loaded = read_mesh(data, kind)
    assert len(loaded.faces) == len(direct) + 2
    fan = {tuple(map(tuple, c)) for c in [fan_vertices[[0, 1, 2]], fan_vertices[[0, 2, 3]]]}
    assert _corner_positions(loaded) == _corner_positions(listed) | _corner_positions(flat) | fan
    assert _corner_positions(flat) == _corner_positions(listed)


def test_khronos_mesh_primitive_modes_reads_its_three_triangle_meshes():
    """Khronos' MeshPrimitiveModes (glTF-Sample-Models, CC0): seven meshes on one hexagon of
    vertices, one per primitive mode. Points and lines are not read; the triangle list
    (6 triangles around vertex 0), the fan 0 1 2 3 4 5 6 1 (the same 6) and the strip
    2 3 1 4 6 5 (4 triangles, vertex 0 unused) are, each with its node's translation, all
    facing +z as the list does."""
    data = (DATA / "khronos_MeshPrimitiveModes.gltf").read_bytes()
    doc = json.loads(data)
    assert [m["primitives"][0]["mode"] for m in doc["meshes"]] == [0, 1, 2, 3, 4, 5, 6]
    loaded = read_mesh(data, "gltf")
    assert loaded.vertices.shape == (21, 3) and loaded.faces.shape == (16, 3)
    v = loaded.vertices[loaded.faces]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (normals[:, 2] > 0).all() and np.allclose(normals[:, :2], 0)
    # each mesh by where its node puts it: x = -2 (list), 0 (strip), 2 (fan), y = -3
    centre_x = v[:, :, 0].mean(axis=1)
    part = np.round((centre_x + 2) / 2).astype(int)
    assert np.bincount(part).tolist() == [6, 4, 6]
    area = 0.5 * np.linalg.norm(normals, axis=1)
    hexagon = 3 * 0.866  # six triangles of base 1 and height 0.866 (the file's sqrt(3)/2)
    np.testing.assert_allclose(np.bincount(part, weights=area), hexagon, rtol=1e-6)
    listed, strip, fan = (loaded.faces[part == k] for k in range(3))
    hexagon_of = {k: loaded.vertices[loaded.faces[part == k]].round(4) for k in range(3)}
    shift = np.array([4.0, 0.0, 0.0])  # the fan's node is 4 to the right of the list's
    np.testing.assert_allclose(hexagon_of[2] - shift, hexagon_of[0], atol=1e-6)
    assert len(listed) == len(fan) == 6 and len(strip) == 4
    assert np.isin(loaded.faces[part == 1], np.flatnonzero(np.isclose(
        np.linalg.norm(loaded.vertices - [0, -3, 0], axis=1), 1.0, atol=1e-3))).all()


@pytest.mark.parametrize("kind", ["gltf", "glb"])
def test_a_strip_without_a_triangle_and_points_alone_are_refused_in_words(kind):
    vertices = np.eye(3)
    with pytest.raises(MeshFileError, match=re.escape(
            "meshes[0].primitives[0]: its triangle strip of 4 indices holds no triangle")):
        read_mesh(_gltf_file(vertices, [(np.array([0, 1, 1, 2]), 5)], kind), kind)
    with pytest.raises(MeshFileError, match=re.escape(
            "no triangle mesh found in the data (points and lines are not read)")):
        read_mesh(_gltf_file(vertices, [(np.array([0, 1, 2]), 0)], kind), kind)
    # beside a readable strip, an empty one is left out
    both = read_mesh(_gltf_file(vertices, [(np.array([0, 1, 1, 2]), 5),
                                           (np.array([0, 1, 2]), 5)], kind), kind)
    assert both.faces.tolist() == [[0, 1, 2]]


def test_a_strips_index_accessor_past_its_buffer_is_named():
    data = json.loads(_gltf_file(np.eye(3), [(np.array([0, 1, 2]), 5)], "gltf"))
    data["accessors"][1]["count"] = 40
    with pytest.raises(MeshFileError, match=re.escape(
            "accessors[1]: its 40 indices run past the end of bufferViews[1]")) as caught:
        read_mesh(json.dumps(data).encode(), "gltf")
    assert caught.value.index == 1


def test_a_strip_without_indices_counting_more_vertices_than_the_file_holds_is_named():
    """Not a MemoryError (a 500 in the service): the count is checked against the file."""
    doc = json.loads(_gltf_file(np.eye(3), [(None, 5)], "gltf"))
    doc["accessors"][0]["count"] = 10**13
    with pytest.raises(MeshFileError, match=re.escape(
            "accessors[0]: the 10000000000000 positions of meshes[0].primitives[0] are more "
            "than the file's")):
        read_mesh(json.dumps(doc).encode(), "gltf")
