"""PLY triangle strips (``element tristrips``, as in alecjacobson/common-3d-test-models'
igea.ply): unrolled into the triangles the strips mean, checked against meshes built
directly, through binary and ASCII PLY files, one record or one record per strip."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from solver.core.errors import MeshFileError
from solver.mesh.io import read_mesh
from solver.mesh.strips import strip_triangles


def grid_strips(rows: int, cols: int) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """A (rows+1) x (cols+1) grid of vertices in z = 0, one strip per row of quads (zig-zag
    v(r+1, c), v(r, c), ...), and the same triangles built directly, counter-clockwise seen
    from +z."""
    ys, xs = np.mgrid[0:rows + 1, 0:cols + 1]
    vertices = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)].astype(float)
    vid = np.arange(xs.size).reshape(rows + 1, cols + 1)
    strips, direct = [], []
    for r in range(rows):
        strips.append(np.stack([vid[r + 1], vid[r]], axis=1).ravel())
        for c in range(cols):
            a, b, d, e = vid[r, c], vid[r, c + 1], vid[r + 1, c], vid[r + 1, c + 1]
            direct += [[d, a, e], [e, a, b]]
    return vertices, strips, np.asarray(direct)


def canonical(faces: np.ndarray) -> set[tuple[int, ...]]:
    """Each triangle rotated to start at its smallest index (orientation kept)."""
    out = set()
    for f in np.asarray(faces):
        k = int(np.argmin(f))
        out.add(tuple(int(x) for x in np.roll(f, -k)))
    return out


def ply_with_strips(vertices: np.ndarray, strips: list[np.ndarray], binary: bool,
                    one_record: bool) -> bytes:
    records = ([np.concatenate([np.append(s, -1) for s in strips])[:-1]] if one_record
               else strips)
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
              f"element vertex {len(vertices)}", "property float x", "property float y",
              "property float z", f"element tristrips {len(records)}",
              "property list int int vertex_indices", "end_header"]
    head = ("\n".join(header) + "\n").encode()
    if binary:
        body = vertices.astype("<f4").tobytes() + b"".join(
            np.int32(len(r)).tobytes() + np.asarray(r, dtype="<i4").tobytes() for r in records)
        return head + body
    lines = [" ".join(f"{x:g}" for x in v) for v in vertices]
    lines += [" ".join(str(int(x)) for x in [len(r), *r]) for r in records]
    return head + ("\n".join(lines) + "\n").encode()


@pytest.mark.parametrize("rows,cols", [(1, 1), (3, 5), (7, 2)])
def test_strips_give_the_grid_triangles_with_one_orientation(rows, cols):
    vertices, strips, direct = grid_strips(rows, cols)
    indices = np.concatenate([np.append(s, -1) for s in strips])
    triangles, strip = strip_triangles(indices)
    assert canonical(triangles) == canonical(direct)
    assert len(triangles) == len(direct)
    normals = trimesh.Trimesh(vertices, triangles, process=False).face_normals
    assert np.allclose(normals[:, 2], 1.0)                      # all counter-clockwise from +z
    assert np.array_equal(np.bincount(strip), np.full(rows, 2 * cols))


def test_joins_with_a_repeated_index_are_dropped():
    # two strips stitched into one record by repeating the last and the first index
    _, strips, direct = grid_strips(2, 3)
    stitched = np.concatenate([strips[0], strips[0][-1:], strips[1][:1], strips[1]])
    triangles, _ = strip_triangles(stitched)
    assert not (np.diff(np.sort(triangles, axis=1), axis=1) == 0).any()
    # two indices of join keep the second strip's parity: its triangles keep their orientation
    assert canonical(triangles) == canonical(direct) and len(triangles) == len(direct)


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("one_record", [True, False])
def test_ply_files_with_tristrips_read_as_their_triangles(binary, one_record):
    vertices, strips, direct = grid_strips(4, 6)
    data = ply_with_strips(vertices, strips, binary, one_record)
    loaded = read_mesh(data, "ply")
    assert np.allclose(loaded.vertices, vertices)
    assert canonical(loaded.faces) == canonical(direct)
    report = loaded.report()
    assert report["file_faces"] == len(strips)                  # a strip is one file face


def test_a_closed_mesh_as_strips_reads_back_closed_and_outward():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    strips = [np.asarray(f) for f in sphere.faces]                # one triangle per strip
    loaded = read_mesh(ply_with_strips(np.asarray(sphere.vertices), strips, True, True), "ply")
    mesh = trimesh.Trimesh(loaded.vertices, loaded.faces, process=False)
    assert canonical(loaded.faces) == canonical(sphere.faces)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


def test_strips_without_a_triangle_are_an_unreadable_file():
    data = ply_with_strips(np.eye(3), [np.array([0, 1])], binary=False, one_record=True)
    with pytest.raises(MeshFileError, match="strips hold no triangle"):
        read_mesh(data, "ply")


def test_strip_records_of_different_lengths():
    vertices, strips, direct = grid_strips(2, 3)
    extra = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    n = len(vertices)
    records = [*strips, np.arange(n, n + 3)]
    loaded = read_mesh(ply_with_strips(np.r_[vertices, extra], records, False, False), "ply")
    assert canonical(loaded.faces) == canonical(np.r_[direct, [[n, n + 1, n + 2]]])
    # Binary records of different lengths in an element other than `face` are beyond
    # trimesh's PLY reader: a 422 unreadable-file that says so, not a wrong mesh.
    binary = ply_with_strips(np.r_[vertices, extra], records, True, False)
    with pytest.raises(MeshFileError, match="cannot parse PLY data") as refused:
        read_mesh(binary, "ply")
    assert refused.value.kind == "unreadable-file"
