"""Binary OFF (``OFF BINARY``): meshes written here word by word in each layout a writer uses
(big- or little-endian, with or without Geomview's face colours, with normals, colours,
texture coordinates or a homogeneous w per vertex) read back as the text OFF of the same
mesh reads; pmp-library's own binary test file (little-endian, an older pmp's writer) read
and reconstructed from its forms; malformed files named.
"""

from __future__ import annotations

import numpy as np
import pytest

import solver
from solver.core.errors import MeshFileError
from solver.mesh.io import read_mesh
from tests.helpers import DATA
from tests.helpers.meshes import rigid_alignment_error


def _binary_off(vertices: np.ndarray, polygons: list[list[int]], *, order: str = ">",
                colours: bool = False, prefix: str = "", extra: int = 0) -> bytes:
    """The words of a binary OFF file, written one record at a time (plain Python: the
    reference the vectorized reader is checked against). ``extra`` float32 words follow
    each vertex's x y z (a normal, a colour...); with ``colours`` each face carries an RGB
    colour after its colour count."""
    words = [np.array([len(vertices), len(polygons), 0], order + "i4").tobytes()]
    for row in np.asarray(vertices, dtype=np.float32):
        words.append(np.concatenate([row, np.full(extra, 0.5, np.float32)]).astype(
            order + "f4").tobytes())
    for face in polygons:
        words.append(np.array([len(face), *face], order + "i4").tobytes())
        if colours:
            words.append(np.array([3], order + "i4").tobytes())
            words.append(np.array([0.1, 0.2, 0.3], order + "f4").tobytes())
    return f"{prefix}OFF BINARY\n".encode() + b"".join(words)


def _text_off(vertices: np.ndarray, polygons: list[list[int]]) -> bytes:
    lines = [f"OFF\n{len(vertices)} {len(polygons)} 0"]
    lines += [" ".join(repr(float(x)) for x in row)
              for row in np.asarray(vertices, np.float32).astype(np.float64)]
    lines += [" ".join(str(i) for i in (len(face), *face)) for face in polygons]
    return ("\n".join(lines) + "\n").encode()


def _meshes() -> dict[str, tuple[np.ndarray, list[list[int]]]]:
    """A family: a shared mesh's triangles, a grid of quads, and mixed polygons."""
    loaded = read_mesh((DATA / "decimated-knight.off").read_bytes(), "off")
    grid = np.array([[x, y, 0.1 * x * y] for y in range(5) for x in range(6)], float)
    quads = [[y * 6 + x, y * 6 + x + 1, (y + 1) * 6 + x + 1, (y + 1) * 6 + x]
             for y in range(4) for x in range(5)]
    mixed = [quads[0], [1, 2, 8], [2, 3, 9, 15, 8], *quads[4:]]
    return {"knight triangles": (loaded.vertices, loaded.faces.tolist()),
            "quads": (grid, quads), "mixed polygons": (grid, mixed)}


MESHES = _meshes()
LAYOUTS = [pytest.param(order, colours, id=f"{'big' if order == '>' else 'little'}-endian"
                        f"{', face colours' if colours else ''}")
           for order in (">", "<") for colours in (False, True)]


@pytest.mark.parametrize("name", MESHES)
@pytest.mark.parametrize(("order", "colours"), LAYOUTS)
def test_binary_off_reads_as_the_text_off_of_the_same_mesh(name, order, colours):
    vertices, polygons = MESHES[name]
    text = read_mesh(_text_off(vertices, polygons), "off")
    binary = read_mesh(_binary_off(vertices, polygons, order=order, colours=colours), "x.off")
    np.testing.assert_array_equal(binary.vertices, text.vertices)
    np.testing.assert_array_equal(binary.faces, text.faces)
    np.testing.assert_array_equal(binary.face_polygon, text.face_polygon)


@pytest.mark.parametrize(("prefix", "extra"), [("N", 3), ("C", 4), ("ST", 2), ("STCN", 9)])
def test_vertex_columns_of_the_keyword_are_skipped(prefix, extra):
    vertices, polygons = MESHES["mixed polygons"]
    binary = read_mesh(_binary_off(vertices, polygons, prefix=prefix, extra=extra), "off")
    np.testing.assert_array_equal(binary.vertices, vertices.astype(np.float32))
    assert binary.polygons == len(polygons) - 1  # every face but one triangle


def test_homogeneous_vertices_are_divided_by_w():
    vertices, polygons = MESHES["quads"]
    data = _binary_off(vertices, polygons, prefix="4", extra=1)  # w = 0.5
    np.testing.assert_allclose(read_mesh(data, "off").vertices,
                               vertices.astype(np.float32) / np.float32(0.5))


def test_pmp_librarys_binary_test_file_is_a_closed_manifold_rebuilt_from_its_forms():
    """pmp-library's data/off/fairing-cross.off (little-endian, as pmp wrote before 3.0): read
    as the mesh pmp's reader makes of it (4,983 vertices, 9,762 triangles, every edge in two
    faces of opposite directions) and rebuilt from its forms to round-off."""
    loaded = read_mesh((DATA / "pmp_fairing-cross_binary.off").read_bytes(), "off")
    assert loaded.vertices.shape == (4983, 3) and loaded.faces.shape == (9762, 3)
    directed = np.sort(loaded.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(directed, axis=0, return_counts=True)
    assert set(counts.tolist()) <= {1, 2}
    forms = solver.fundamental_forms(loaded.vertices, loaded.faces)
    result = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                vertex_map=forms.vertex_map, weld_map=forms.weld_map,
                                placement=forms.placement, n_vertices=len(loaded.vertices))
    assert rigid_alignment_error(result.vertices, loaded.vertices) < 1e-8


@pytest.mark.parametrize(("data", "words"), [
    (b"OFF BINARY\n" + np.array([4, 9, 0], ">i4").tobytes(), "the counts do not fit"),
    (_binary_off(*MESHES["quads"])[:-10], "the face records fit neither layout"),
    (_binary_off(*MESHES["quads"]) + bytes(8), "the face records fit neither layout"),
    (_binary_off(np.eye(3), [[0, 1]]) + bytes(4), "face 0 has 2 corners, fewer than 3"),
    (_binary_off(np.eye(3), [[0, 1, 2]], prefix="n"), "nOFF"),
    (_binary_off(np.array([[0, 0, np.inf], [1, 0, 0], [0, 1, 0]]), [[0, 1, 2]]),
     "vertex 0 has a non-finite coordinate"),
], ids=["counts", "cut", "trailing words", "two corners", "dimension", "infinite"])
def test_malformed_binary_off_is_named(data, words):
    with pytest.raises(MeshFileError, match=words) as caught:
        read_mesh(data, "bad.off")
    assert caught.value.file_type == "off"
