"""The OFF and OBJ readers' numpy block path (issue 45): the same arrays as trimesh and as the
record-by-record path on shared meshes and generated polygon files, and the record-by-record
path's errors (with line numbers) for every file the block path does not take.

Each file is read twice: as written, which the block path takes, and with a comment line
inserted among its records, which the block path leaves to the record-by-record parser
(checked: the block path returns None for it). Both must give the same arrays, and those
must be trimesh's (an independent parser) or, for polygons, the fan triangulation written
out in the test.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from solver.core.errors import MeshFileError
from solver.mesh import mesh_readers, obj_reader
from solver.mesh.io import read_mesh, save_mesh

MESHES = Path(__file__).resolve().parents[3] / "shared" / "meshes"
if not MESHES.is_dir():
    MESHES = Path("/work/shared/meshes")
SHARED = ["bunny.off", "cactus.off", "decimated-knight.off", "torus.off", "armadillo.obj",
          "rocker-arm.obj", "stanford-bunny.obj"]


def _with_comment(data: bytes, fmt: str) -> bytes:
    """``data`` with a comment the block readers leave to the record-by-record parsers: an
    OFF comment line among the records (not a record), an OBJ comment after a ``v``
    line's numbers (a whole-line OBJ comment is read in blocks)."""
    lines = data.split(b"\n")
    if fmt == "obj":
        at = next(k for k, line in enumerate(lines) if line.startswith(b"v "))
        return b"\n".join([*lines[:at], lines[at] + b" # a comment", *lines[at + 1:]])
    return b"\n".join([*lines[:5], b"# a comment among the records", *lines[5:]])


def _blocks(fmt: str):
    return mesh_readers._off_blocks if fmt == "off" else obj_reader._obj_blocks


@pytest.mark.parametrize("name", SHARED)
def test_shared_meshes_read_as_trimesh_reads_them(name: str) -> None:
    path = MESHES / name
    fmt = path.suffix[1:]
    expected = trimesh.load(path, process=False, maintain_order=True)
    # trimesh splits OBJ vertices by their vt/vn: compare through a file of v and f only
    data = (save_mesh(expected.vertices, expected.faces, fmt) if fmt == "obj"
            else path.read_bytes())
    for variant in (data, _with_comment(data, fmt)):
        loaded = read_mesh(variant, fmt)
        np.testing.assert_array_equal(loaded.vertices, expected.vertices)
        np.testing.assert_array_equal(loaded.faces, expected.faces)
    assert _blocks(fmt)(data) is not None
    assert _blocks(fmt)(_with_comment(data, fmt)) is None


def _fan(polygons: list[list[int]]) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangles (a, b, c), (a, c, d), ... of each polygon and their polygon, in a loop."""
    triangles, owner = [], []
    for k, poly in enumerate(polygons):
        for t in range(1, len(poly) - 1):
            triangles.append([poly[0], poly[t], poly[t + 1]])
            owner.append(k)
    return np.array(triangles, dtype=np.int64), np.array(owner, dtype=np.int64)


def _polygon_files(corners: list[int], seed: int) -> tuple[np.ndarray, list[list[int]], dict]:
    """Random vertices and polygons of the given corner counts, as OFF and OBJ files."""
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(40, 3))
    polygons = [list(rng.choice(40, size=k, replace=False)) for k in corners]
    off = [f"OFF\n{len(vertices)} {len(polygons)} 0"]
    off += [" ".join(repr(float(x)) for x in row) for row in vertices]
    off += [" ".join(map(str, [len(p), *p])) for p in polygons]
    obj = ["v " + " ".join(repr(float(x)) for x in row) for row in vertices]
    obj += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in p) for p in polygons]
    return vertices, polygons, {"off": "\n".join(off).encode() + b"\n",
                                "obj": "\n".join(obj).encode() + b"\n"}


@pytest.mark.parametrize("corners", [[3] * 30, [4] * 30, [6] * 12, [3, 4, 5, 3, 8, 4]])
@pytest.mark.parametrize("fmt", ["off", "obj"])
def test_polygon_files_are_fan_triangulated_on_both_paths(corners: list[int], fmt: str) -> None:
    vertices, polygons, files = _polygon_files(corners, seed=len(corners) * corners[-1])
    triangles, owner = _fan(polygons)
    data = files[fmt]
    for variant in (data, _with_comment(data, fmt)):
        loaded = read_mesh(variant, fmt)
        np.testing.assert_array_equal(loaded.vertices, vertices)
        np.testing.assert_array_equal(loaded.faces, triangles)
        np.testing.assert_array_equal(loaded.face_polygon, owner)
    uniform = len(set(corners)) == 1
    assert (_blocks(fmt)(data) is not None) == uniform  # mixed polygons: record by record


@pytest.mark.parametrize("fmt", ["off", "obj"])
def test_obj_and_off_of_a_large_mesh_agree_with_ply(fmt: str) -> None:
    """A 20K-face subdivided sphere through OFF/OBJ (text, %.17g) and binary PLY: the text
    readers' blocks give the exact float64 numbers and the same faces."""
    mesh = trimesh.creation.icosphere(subdivisions=5)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    ply = read_mesh(save_mesh(vertices, faces, "ply"), "ply")
    data = save_mesh(vertices, faces, fmt)
    assert _blocks(fmt)(data) is not None
    text = read_mesh(data, fmt)
    np.testing.assert_array_equal(text.vertices, ply.vertices)
    np.testing.assert_array_equal(text.faces, ply.faces)


@pytest.mark.parametrize(("data", "words"), [
    (b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1\n3 0 1 2\n", "line 5: vertex 2 has 2 coordinates"),
    (b"OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1\n", "line 7"),
    (b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 x\n", "line 6"),
    (b"OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "1 of the 2 faces"),
])
def test_malformed_off_is_named_at_its_line(data: bytes, words: str) -> None:
    assert mesh_readers._off_blocks(data) is None
    with pytest.raises(MeshFileError, match=words):
        read_mesh(data, "off")


@pytest.mark.parametrize(("data", "words"), [
    (b"v 0 0 0\nv 1 0 0\nv 0 1\nf 1 2 3\n", "line 3: vertex needs 3 coordinates"),
    (b"v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n",
     "line 3: face 0 has vertex index 3, but only 2 vertices are defined before its line"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "line 4: face with fewer than 3 vertices"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n",
     "line 4: face 0 has vertex index 0, but OBJ indices start at 1"),
])
def test_malformed_obj_is_named_at_its_line(data: bytes, words: str) -> None:
    assert obj_reader._obj_blocks(data) is None
    with pytest.raises(MeshFileError, match=words):
        read_mesh(data, "obj")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stl_merge_matches_numpy_unique(seed: int) -> None:
    """merge_identical (a hash sort) against np.unique(axis=0) renumbered by first
    occurrence, on corners drawn from a few positions (many repeats, -0.0 among them)."""
    rng = np.random.default_rng(seed)
    positions = rng.integers(-2, 3, size=(3000, 3)) * 0.5
    positions[rng.random(positions.shape) < 0.1] = -0.0
    faces = rng.integers(0, len(positions), size=(2000, 3))
    merged, merged_faces = mesh_readers.merge_identical(positions, faces)
    v = positions + 0.0
    unique, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    np.testing.assert_array_equal(merged, unique[order])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    np.testing.assert_array_equal(merged_faces, rank[inverse.ravel()][faces])
    np.testing.assert_array_equal(merged[merged_faces], v[faces])
