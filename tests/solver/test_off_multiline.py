"""OFF records over several lines (libigl-tutorial-data's inspired_mesh_quads_*.off write each
quad's indices on lines of their own), read as :mod:`solver.mesh.mesh_readers` states: a
record starts a line; on one line it may carry further columns (a colour), over several
lines it ends with its last line. Checked against a plain-Python reader of that rule, and
against the same mesh written one record per line.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from solver.core.errors import MeshFileError
from solver.mesh import mesh_readers
from solver.mesh.io import read_mesh
from tests.helpers import REPO


def _reference(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The OFF rule record by record in plain Python: vertices, fan triangles, their face."""
    lines = [line.split("#", 1)[0].split() for line in data.decode().splitlines()]
    lines = [line for line in lines if line]
    head = lines[0][1:] or lines[1]
    n_vertices, n_faces = int(head[0]), int(head[1])
    at = 1 if lines[0][1:] else 2

    def record(width: int | None) -> list[str]:
        nonlocal at
        tokens = list(lines[at])
        at += 1
        need = width or int(tokens[0]) + 1
        if len(tokens) >= need:
            return tokens[:need]
        while len(tokens) < need:
            tokens += lines[at]
            at += 1
        assert len(tokens) == need, "a record over several lines ends with its line"
        return tokens

    vertices = [[float(x) for x in record(3)] for _ in range(n_vertices)]
    triangles, owner = [], []
    for face in range(n_faces):
        corners = [int(i) for i in record(None)[1:]]
        for t in range(1, len(corners) - 1):
            triangles.append([corners[0], corners[t], corners[t + 1]])
            owner.append(face)
    return np.array(vertices), np.array(triangles), np.array(owner)


def _assert_reads_as_reference(data: bytes) -> None:
    loaded = read_mesh(data, "off")
    vertices, triangles, owner = _reference(data)
    np.testing.assert_array_equal(loaded.vertices, vertices)
    np.testing.assert_array_equal(loaded.faces, triangles)
    np.testing.assert_array_equal(loaded.face_polygon, owner)


def test_a_libigl_quad_file_with_one_index_a_line_reads() -> None:
    """libigl-tutorial-data's inspired_mesh_quads_Conjugate.off (tests/data/README.md)."""
    data = (REPO / "tests" / "data" / "inspired_mesh_quads_Conjugate.off").read_bytes()
    _assert_reads_as_reference(data)
    loaded = read_mesh(data, "off")
    assert loaded.report() == {"file_faces": 1633, "triangulated_polygons": 1633,
                               "triangles": 2 * 1633}


SPREAD = b"""OFF
# a square pyramid over a split base
6 5 0
0 0 0
1 0
  0
1 1 0
0 1 0
0.5 0.5 1
0.5 0.5 0
4 0 1
2 3

3 0 1 4
3 1
2
4
3 2 3 4
3
3 0 4 # the last face over two lines
"""


def test_quads_and_triangles_over_several_lines() -> None:
    loaded = read_mesh(SPREAD, "off")
    assert loaded.vertices.tolist()[1] == [1.0, 0.0, 0.0]
    assert loaded.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4], [1, 2, 4], [2, 3, 4],
                                     [3, 0, 4]]
    assert loaded.face_polygon.tolist() == [0, 0, 1, 2, 3, 4]
    _assert_reads_as_reference(SPREAD)


ONE_LINE = b"OFF\n5 3 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 2 0\n"


@pytest.mark.parametrize("faces", [
    b"3 0 1 2 255 0 0\n3 0 2 3 0 255 0\n3 1 4 2 0 0 255\n",  # numpy blocks
    b"4 0 1 2 3 0.5 0.5 0.5 1\n3 1 4 2 1 0 0\n3 0 1 4\n",  # record by record
])
def test_colour_columns_after_a_face_on_one_line_are_ignored(faces: bytes) -> None:
    data = ONE_LINE + faces
    assert (mesh_readers._off_blocks(data) is None) == faces.startswith(b"4")
    loaded = read_mesh(data, "off")
    expected = [[0, 1, 2], [0, 2, 3], [1, 4, 2]] if faces.startswith(b"3 0 1 2") else \
        [[0, 1, 2], [0, 2, 3], [1, 4, 2], [0, 1, 4]]
    assert loaded.faces.tolist() == expected


def test_a_colour_after_a_face_on_one_line_in_a_file_of_spread_records() -> None:
    data = ONE_LINE + b"3 0 1\n2\n4 0 1 2 3 255 0 0\n3 1 4\n2\n"
    assert read_mesh(data, "off").faces.tolist() == [[0, 1, 2], [0, 1, 2], [0, 2, 3],
                                                     [1, 4, 2]]


@pytest.mark.parametrize("seed", range(4))
def test_random_line_breaks_read_as_the_same_mesh(seed: int) -> None:
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(60, 3))
    polygons = [rng.choice(60, size=k, replace=False) for k in rng.integers(3, 9, 200)]

    def written(spread: bool) -> bytes:
        out = [f"OFF\n{len(vertices)} {len(polygons)} 0\n"]
        for record in [[repr(float(x)) for x in row] for row in vertices] + \
                      [[str(len(p)), *map(str, p)] for p in polygons]:
            breaks = rng.random(len(record)) < (0.4 if spread else 0.0)
            out.append("".join(word + ("\n" if cut else " ")
                               for word, cut in zip(record, breaks, strict=True)) + "\n")
            if rng.random() < 0.1:
                out.append("# a comment\n\n")
        return "".join(out).encode()

    spread, plain = written(True), written(False)
    _assert_reads_as_reference(spread)
    a, b = read_mesh(spread, "off"), read_mesh(plain, "off")
    np.testing.assert_array_equal(a.vertices, vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.face_polygon, b.face_polygon)


CUT = SPREAD.rsplit(b"3\n3 0 4", 1)[0]


@pytest.mark.parametrize(("data", "words"), [
    (CUT, "the file ends after 4 of the 5 faces its header announces"),
    (CUT + b"3\n3 0", "the file ends inside face 4 (from line 19, 4 numbers; truncated?)"),
    (CUT + b"3\n3 0 4 1 0 0", "line 20: face 4 (from line 19, 4 numbers) ends before this "
                              "line does ('1' follows)"),
    (CUT + b"3\n3 0 x", "line 20: face 4 has a vertex index that is not a whole number: 'x'"),
    (CUT + b"3.5\n3 0 4", "line 19: face 4 starts with '3.5', not a whole number of corners"),
    (CUT + b"2\n3 0", "line 19: face 4 has fewer than 3 vertices"),
    (CUT + b"99999999999999999999\n3 0", "the file ends inside face 4 (from line 19"),
])
def test_a_malformed_file_of_spread_records_is_named_at_its_record(data: bytes,
                                                                   words: str) -> None:
    with pytest.raises(MeshFileError) as info:
        read_mesh(data, "off")
    assert info.value.file_type == "off"
    assert info.value.reason.startswith(f"cannot parse OFF data: {words}")


@pytest.mark.parametrize(("head", "words"), [
    (b"OFF\n10000000000000 1 0\n", "the file ends after 4 of the 10000000000000 vertices"),
    (b"OFF\n3 10000000000000 0\n", "the file ends after 1 of the 10000000000000 faces"),
    (b"OFF\n-3 1 0\n", "the header's counts (-3 vertices, 1 faces) must not be negative"),
])
def test_header_counts_beyond_the_file_or_negative(head: bytes, words: str) -> None:
    """Told at once: no array of the header's size is made."""
    data = head + b"0 0 0\n1 0\n0\n0 1 0\n3 0 1 2\n"
    with pytest.raises(MeshFileError, match=re.escape(words)):
        read_mesh(data, "off")


def test_a_short_face_in_a_file_of_one_line_records_is_named_as_ever() -> None:
    """A face short of its count in a file of records one per line is that record's fault,
    not the start of a record over several lines (the next line would end it early)."""
    data = ONE_LINE + b"3 0 1 2\n3 0 2\n3 1 4 2\n3 0 1 4\n"
    with pytest.raises(MeshFileError, match="line 9: face 1 lists 2 vertex indices, its "
                                            "count says 3"):
        read_mesh(data, "off")


def test_off_non_finite_coordinate_names_vertex_line_and_value() -> None:
    for data in (ONE_LINE.replace(b"1 1 0", b"1 nan 0") + b"3 0 1 2\n3 0 2 3\n3 1 4 2\n",
                 ONE_LINE.replace(b"1 1 0", b"1 1e999\n0") + b"3 0 1 2\n3 0 2 3\n3 1 4 2\n"):
        with pytest.raises(MeshFileError) as info:
            read_mesh(data, "off")
        value = "nan" if b"nan" in data else "1e999"
        assert info.value.reason == f"line 5: vertex 2 has a non-finite coordinate {value!r}"
        assert info.value.index == 2
        assert info.value.details == {"line": 5, "value": value}


def test_follow_matches_a_loop() -> None:
    rng = np.random.default_rng(5)
    lines = 500
    after = np.minimum(np.arange(lines) + rng.integers(1, 4, lines), lines)
    for start, steps in [(0, 1), (0, 200), (7, 333), (lines, 3)]:
        expected, at = [], start
        for _ in range(steps):
            expected.append(at)
            at = lines if at >= lines else int(after[at])
        assert mesh_readers._follow(after, start, steps).tolist() == expected
