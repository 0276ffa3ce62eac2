"""solver.mesh.io: mesh files in, mesh files out, with the file's vertex order and count kept."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from solver.core.errors import (
    IndexOutOfRangeError,
    NonFiniteValueError,
    ShapeMismatchError,
    SolverInputError,
)
from solver.mesh.io import (
    LOAD_FORMATS,
    SAVE_FORMATS,
    MeshFileError,
    UnsupportedFormatError,
    load_mesh,
    load_mesh_file,
    resolve_format,
    save_mesh,
)

MESHES = Path(__file__).resolve().parents[3] / "shared" / "meshes"  # shared/ beside the repo
if not MESHES.is_dir():
    MESHES = Path("/work/shared/meshes")


@pytest.fixture(scope="module")
def permuted() -> tuple[np.ndarray, np.ndarray]:
    """Icosphere with shuffled vertex order plus one unreferenced vertex in the middle."""
    m = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(7)
    perm = rng.permutation(len(m.vertices))
    v = m.vertices[perm]
    f = np.argsort(perm)[m.faces]
    k = 17  # insert the unreferenced vertex at index k
    v = np.vstack([v[:k], [[2.5, -1.25, 0.125]], v[k:]])
    f = np.where(f >= k, f + 1, f)
    return v.astype(np.float64), f.astype(np.int64)


def _trimesh_bytes(v: np.ndarray, f: np.ndarray, file_type: str) -> bytes:
    out = trimesh.Trimesh(v, f, process=False).export(file_type=file_type)
    return out.encode() if isinstance(out, str) else bytes(out)


# ------------------------------------------------------------------ order and count kept


@pytest.mark.parametrize("fmt", ["obj", "off", "ply"])
def test_files_written_by_trimesh_keep_order(permuted: tuple[np.ndarray, np.ndarray],
                                             fmt: str) -> None:
    v, f = permuted
    v2, f2 = load_mesh(_trimesh_bytes(v, f, fmt), fmt)
    assert v2.dtype == np.float64 and f2.dtype == np.int64
    assert v2.shape == v.shape  # unreferenced vertex kept
    np.testing.assert_allclose(v2, v, atol=1e-6)  # trimesh writes limited precision
    np.testing.assert_array_equal(f2, f)


@pytest.mark.parametrize("fmt", ["obj", "off", "ply"])
def test_save_load_round_trip_is_exact(permuted: tuple[np.ndarray, np.ndarray],
                                       fmt: str) -> None:
    v, f = permuted
    v = v * np.pi  # digits that a short decimal would lose
    v2, f2 = load_mesh(save_mesh(v, f, fmt), fmt)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)


def test_saved_files_read_by_trimesh(permuted: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = permuted
    for fmt in ("obj", "off", "ply"):
        m = trimesh.load(io.BytesIO(save_mesh(v, f, fmt)), file_type=fmt, process=False,
                         maintain_order=True)
        np.testing.assert_array_equal(m.vertices, v)
        np.testing.assert_array_equal(m.faces, f)


def test_glb_round_trip(permuted: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = permuted
    for data in (save_mesh(v, f, "glb"), _trimesh_bytes(v, f, "glb")):
        v2, f2 = load_mesh(data, "glb")
        np.testing.assert_array_equal(v2, v.astype(np.float32))  # glTF positions are float32
        np.testing.assert_array_equal(f2, f)


def test_stl_merges_identical_positions_in_first_occurrence_order(
        permuted: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = permuted
    data = save_mesh(v, f, "stl")
    assert len(data) == 84 + 50 * len(f)  # binary STL
    v2, f2 = load_mesh(data, "stl")
    used = np.unique(f)
    assert len(v2) == len(used)  # merged; the unreferenced vertex cannot be in an STL
    # vertex order = order of first appearance in the face corners
    _, first = np.unique(f.ravel(), return_index=True)
    expected_order = f.ravel()[np.sort(first)]
    np.testing.assert_array_equal(v2, v[expected_order].astype(np.float32))
    np.testing.assert_array_equal(v2[f2], v[f].astype(np.float32))
    # connected again: every edge shared by two faces (closed sphere)
    edges = np.sort(f2[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_stl_negative_zero_merged() -> None:
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    tri2 = np.array([[-0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    # write a binary STL by hand: 80-byte header, count, (normal, 3 corners, attr) per face
    body = b"".join(struct.pack("<12fH", 0, 0, 1, *t.ravel(), 0) for t in (tri, tri2))
    v2, f2 = load_mesh(b"\0" * 80 + struct.pack("<I", 2) + body, "mesh.STL")
    assert len(v2) == 4
    np.testing.assert_array_equal(f2, [[0, 1, 2], [0, 2, 3]])


# ------------------------------------------------------------------ OBJ specifics


OBJ_WITH_VT_VN = b"""# quad split into two triangles, seams in vt and vn
mtllib missing.mtl
o first
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 9 9 9
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
vn 0 0 1
vn 0 0 -1
usemtl a
f 1/1/1 2/2/1 3/3/1
g second
usemtl b
f 1/5/2 3/4/2 4/1/2
f 2//1 3//2 -1//1
"""


def test_obj_vt_vn_do_not_split_vertices() -> None:
    v, f = load_mesh(OBJ_WITH_VT_VN, "obj")
    assert v.shape == (5, 3)  # every v line, incl. the unreferenced-until-last one
    np.testing.assert_array_equal(v[4], [9, 9, 9])
    np.testing.assert_array_equal(f, [[0, 1, 2], [0, 2, 3], [1, 2, 4]])
    # trimesh itself would split on the vt/vn seams and give more vertices
    m = trimesh.load(io.BytesIO(OBJ_WITH_VT_VN), file_type="obj", process=False,
                     force="mesh")
    assert len(m.vertices) != 5


def test_obj_polygons_negative_indices_and_unreferenced() -> None:
    data = b"""v 0 0 0
v 1 0 0
v 2 1 0
v 1 2 0
v 0 1 0
v 7 7 7
f -6 -5 -4 -3 -2
v 3 3 3
"""
    v, f = load_mesh(data, "obj")
    assert v.shape == (7, 3)
    np.testing.assert_array_equal(f, [[0, 1, 2], [0, 2, 3], [0, 3, 4]])  # fan


def test_obj_unreferenced_vertices_kept_on_real_file() -> None:
    """stanford-bunny.obj: 35947 `v` lines, only 34834 referenced (see INDEX.md)."""
    v, f = load_mesh_file(MESHES / "stanford-bunny.obj")
    assert v.shape == (35947, 3)
    assert f.shape == (69451, 3)
    assert len(np.unique(f)) == 34834


def test_obj_matches_trimesh_on_plain_file() -> None:
    path = MESHES / "rocker-arm.obj"
    v, f = load_mesh_file(path)
    m = trimesh.load(path, process=False, maintain_order=True)
    np.testing.assert_array_equal(v, m.vertices)
    np.testing.assert_array_equal(f, m.faces)


@pytest.mark.parametrize("data, what", [
    (b"v 1 2\nf 1 1 1\n", "3 coordinates"),
    (b"v 1 2 3\nv 0 0 0\nf 1 2\n", "fewer than 3"),
    (b"v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n", "only 2 vertices are defined before"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "OBJ indices start at 1"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "line 4: face index 'x' is not a whole number"),
    (b"v 0 0 zz\n", "line 1: vertex coordinate 'zz' is not a number"),
    (b"# c\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n\nf 1 2 3.5 # q\n",
     "line 8: face index '3.5' is not a whole number"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1e5x 0 # q\nf 1 2 3\n",
     "line 4: vertex coordinate '1e5x' is not a number"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    (b"v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", "non-finite"),
])
def test_obj_errors(data: bytes, what: str) -> None:
    with pytest.raises(MeshFileError, match=what) as info:
        load_mesh(data, "obj")
    assert info.value.file_type == "obj"
    assert what in info.value.reason


# ------------------------------------------------------------------ OFF / PLY specifics


def test_bar_off_vertex_count() -> None:
    v, f = load_mesh_file(MESHES / "bar.off")
    assert v.shape == (6084, 3) and f.shape == (12106, 3)
    sel = (MESHES / "bar.sel").read_text().split("\n")
    labels = [line for line in sel if line.strip() and not line.startswith("#")]
    assert len(labels) == len(v)  # .sel files index vertices in OFF order


def test_off_quads_triangulated() -> None:
    data = b"OFF\n# comment\n5 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 4 4\n4 0 1 2 3\n"
    v, f = load_mesh(data, "off")
    assert v.shape == (5, 3)
    assert f.shape == (2, 3)
    assert set(np.unique(f)) == {0, 1, 2, 3}


def test_off_index_out_of_range() -> None:
    with pytest.raises(MeshFileError):
        load_mesh(b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n", "off")


def test_ply_ascii_with_unreferenced_vertex() -> None:
    data = b"""ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 1
property list uchar int vertex_indices
end_header
5 5 5
0 0 0
1 0 0
0 1 0
3 1 2 3
"""
    v, f = load_mesh(data, "ply")
    np.testing.assert_array_equal(v[0], [5, 5, 5])
    np.testing.assert_array_equal(f, [[1, 2, 3]])


def test_ply_point_cloud_rejected() -> None:
    data = (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n0 0 0\n")
    with pytest.raises(MeshFileError):
        load_mesh(data, "ply")


# ------------------------------------------------------------------ GLB scenes


def test_glb_multiple_meshes_are_parts_of_one_mesh() -> None:
    # Issue 40: a multi-part model is read whole, its parts in scene order, in place.
    a = trimesh.creation.box()
    b = trimesh.creation.icosphere(1)
    b.apply_translation([3, 0, 0])
    data = trimesh.Scene([a, b]).export(file_type="glb")
    v, f = load_mesh(data, "glb")
    assert v.shape == (len(a.vertices) + len(b.vertices), 3)
    assert f.shape == (len(a.faces) + len(b.faces), 3)
    found = sorted([np.round(v[: len(a.vertices)].mean(axis=0), 5).tolist(),
                    np.round(v[len(a.vertices):].mean(axis=0), 5).tolist()])
    assert found[1][0] == pytest.approx(3.0, abs=1e-5)  # the sphere kept its place


def test_glb_node_transform_applied() -> None:
    m = trimesh.creation.icosphere(1)
    scene = trimesh.Scene()
    shift = np.eye(4)
    shift[:3, 3] = [10.0, 0.0, -2.0]
    scene.add_geometry(m, transform=shift)
    v, f = load_mesh(scene.export(file_type="glb"), "model/gltf-binary")
    np.testing.assert_allclose(v, m.vertices.astype(np.float32) + shift[:3, 3], atol=1e-6)
    np.testing.assert_array_equal(f, m.faces)


# ------------------------------------------------------------------ errors and formats


@pytest.mark.parametrize("fmt", LOAD_FORMATS)
@pytest.mark.parametrize("data", [b"\x00\x01\x02garbage\xff" * 37, b"hello world\n", b"",
                                  b"   \n"], ids=["binary", "text", "empty", "blank"])
def test_garbage_raises_mesh_file_error(fmt: str, data: bytes) -> None:
    with pytest.raises(MeshFileError) as info:
        load_mesh(data, fmt)
    assert isinstance(info.value, SolverInputError) and isinstance(info.value, ValueError)
    assert not isinstance(info.value, UnsupportedFormatError)
    assert info.value.reason
    assert info.value.to_dict()["kind"] == "unreadable-file"
    assert info.value.file_type == fmt and str(info.value).startswith(f"{fmt}: ")


def test_a_file_error_names_the_file_as_the_caller_knows_it() -> None:
    with pytest.raises(MeshFileError) as info:
        load_mesh(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "obj")
    error = info.value.located(field="file_a", file_name="tri.obj")
    reason = "line 4: face 0 has vertex index 9, but only 3 vertices are defined before its line"
    assert str(error) == f"tri.obj: obj: {reason}"
    assert error.element() == {"field": "file_a", "index": 0, "line": 4, "value": 9,
                               "reason": reason}


OBJ_VERTICES = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n"


@pytest.mark.parametrize(("faces", "face", "line", "value", "why"), [
    (b"f 1 2 9\n", 0, 4, 9, "9, but only 3 vertices are defined before its line"),
    (b"f 1 2 3\nf 1 2 0\n", 1, 5, 0,
     "0, but OBJ indices start at 1 (negative ones count back from the last vertex defined)"),
    (b"f 1 2 3\n\nf -1 -2 -9\n", 1, 6, -9,
     "-9, which counts back past the first vertex (only 3 are defined before its line)"),
    (b"f 1/1/1 2/2/2 4/3/3\n", 0, 4, 4, "4, but only 3 vertices are defined before its line"),
    (b"f 1 2 3\nf 1 2 3 4 # a quad\n", 1, 5, 4, "4, but only 3 vertices"),
])
def test_obj_index_errors_name_the_face_its_line_and_the_index(
        faces: bytes, face: int, line: int, value: int, why: str) -> None:
    with pytest.raises(MeshFileError) as info:
        load_mesh(OBJ_VERTICES + faces, "obj")
    assert info.value.reason.startswith(f"line {line}: face {face} has vertex index {why}")
    assert info.value.index == face
    assert info.value.details == {"line": line, "value": value}


@pytest.mark.parametrize("data", [
    OBJ_VERTICES.replace(b"v 1 0 0", b"v 1 -inf 0") + b"f 1 2 3\n",  # numpy blocks
    OBJ_VERTICES.replace(b"v 1 0 0", b"v 1 -inf 0 # q") + b"vt 0 0\nf 1/1 2/1 3/1\n",
])
def test_obj_non_finite_coordinate_names_the_vertex_its_line_and_value(data: bytes) -> None:
    with pytest.raises(MeshFileError) as info:
        load_mesh(data, "obj")
    assert info.value.reason == "line 2: vertex 1 has a non-finite coordinate '-inf'"
    assert info.value.index == 1 and info.value.details == {"line": 2, "value": "-inf"}


def test_a_vertex_record_at_fault_is_the_index() -> None:
    with pytest.raises(MeshFileError) as info:
        load_mesh(b"v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", "obj")
    assert info.value.index == 1 and "vertex 1" in info.value.reason


@pytest.mark.parametrize("name", ["mesh.dae", "fbx", "", "noext", "model/vnd.collada+xml"])
def test_unsupported_format(name: str) -> None:
    with pytest.raises(UnsupportedFormatError) as info:
        load_mesh(b"v 0 0 0\n", name)
    assert info.value.to_dict()["kind"] == "unsupported-file-type"
    assert info.value.details["supported"] == list(LOAD_FORMATS)
    with pytest.raises(UnsupportedFormatError):
        save_mesh(np.zeros((3, 3)), [[0, 1, 2]], name)



def test_gltf_is_written_by_the_one_writer_and_reads_back() -> None:
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.25, 0.5, 1]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    for fmt in ("glb", "gltf"):
        data = save_mesh(V, F, fmt)
        W, G = load_mesh(data, fmt)
        np.testing.assert_array_equal(G, F)
        np.testing.assert_array_equal(W, V.astype(np.float32))  # glTF stores float32


@pytest.mark.parametrize("given, expected", [
    ("bunny.OFF", "off"), (".obj", "obj"), ("PLY", "ply"), ("dir.v2/mesh.stl", "stl"),
    ("model/gltf-binary", "glb"), ("model/gltf+json", "gltf"), ("scan.glb", "glb"),
])
def test_resolve_format(given: str, expected: str) -> None:
    assert resolve_format(given) == expected


def test_save_formats_all_load_back(permuted: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = permuted
    for fmt in SAVE_FORMATS:
        v2, f2 = load_mesh(save_mesh(v, f, fmt), fmt)
        np.testing.assert_allclose(v2[f2], v[f], atol=1e-6)


def test_save_input_errors() -> None:
    v = np.zeros((3, 3))
    with pytest.raises(ShapeMismatchError):
        save_mesh(v[:, :2], [[0, 1, 2]], "off")
    with pytest.raises(IndexOutOfRangeError):
        save_mesh(v, [[0, 1, 3]], "off")
    with pytest.raises(NonFiniteValueError):
        save_mesh(np.full((3, 3), np.inf), [[0, 1, 2]], "obj")


def test_load_mesh_file(tmp_path: Path, permuted: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = permuted
    path = tmp_path / "x.ply"
    path.write_bytes(save_mesh(v, f, "ply"))
    v2, f2 = load_mesh_file(path)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)


def test_off_polygons_fan_triangulated_like_obj_and_ply() -> None:
    """Issue 40: the same quads in OFF, OBJ and PLY give the same triangles, in file order,
    and read_mesh says which file face each comes from; counts glued to the header too."""
    from solver.mesh.io import read_mesh

    off = b"OFF8 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 0 0\n2 1 0\n3 2 0\n3 3 0\n" \
          b"5 1 4 5 6 2 255 0 0\n4 0 1 2 3\n"
    obj = b"".join(f"v {x} {y} 0\n".encode() for x, y in
                   [(0, 0), (1, 0), (1, 1), (0, 1), (2, 0), (2, 1), (3, 2), (3, 3)])
    obj += b"f 2 5 6 7 3\nf 1 2 3 4\n"
    ply = (b"ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
           b"property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
           b"end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 0 0\n2 1 0\n3 2 0\n3 3 0\n"
           b"5 1 4 5 6 2\n4 0 1 2 3\n")
    want = [[1, 4, 5], [1, 5, 6], [1, 6, 2], [0, 1, 2], [0, 2, 3]]
    for data, fmt in ((off, "off"), (obj, "obj"), (ply, "ply")):
        loaded = read_mesh(data, fmt)
        assert loaded.faces.tolist() == want, fmt
        assert loaded.face_polygon.tolist() == [0, 0, 0, 1, 1] and loaded.polygons == 2
        assert loaded.report() == {"file_faces": 2, "triangulated_polygons": 2, "triangles": 5}
