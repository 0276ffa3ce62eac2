"""The OBJ reader behind :mod:`solver.mesh.formats`' ``obj`` format: positions from every
``v`` line, triangles from the ``v`` index of every ``f`` entry (k-gons fan-triangulated), read
in numpy blocks where the file's layout allows and line by line otherwise, with errors that
name the line at fault. The rules are :mod:`solver.mesh.io`'s docstring.
"""

from __future__ import annotations

import re
from typing import Final

import numpy as np

from ..core.errors import MeshFileError
from .mesh_readers import fan_triangulate, number_block

_OBJ_REF_TAIL: Final = re.compile(r"/\S*")
"""The ``/vt/vn`` tail of an OBJ face entry."""
_OBJ_REF_TAIL_BYTES: Final = re.compile(rb"/\S*")
"""The same, in bytes."""
_INTEGER: Final = re.compile(r"[+-]?\d+")
"""A face index as numpy reads it."""
_FLOAT: Final = re.compile(r"[+-]?(?:\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?"
                           r"|inf(?:inity)?|nan)", re.IGNORECASE)
"""A coordinate as numpy reads it."""
_TOKEN: Final = re.compile(r"\S+")


def parse_obj(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions from every ``v`` line, triangles from the ``v`` index of every ``f`` entry.

    Args:
        data: The OBJ file.

    Returns:
        (n, 3) float64 vertices in ``v``-line order, (m, 3) int64 faces (0-based; each
        k-gon fan-triangulated, :func:`fan_triangulate`) and (m,) int64 the ``f`` record
        of each triangle. A file of plain ``v`` and ``f`` lines whose faces all have the same
        corner count is read in numpy blocks (:func:`_obj_blocks`); any other file, and
        every malformed one, line by line (the errors name the line at fault).
    """
    blocks = _obj_blocks(data)
    if blocks is not None and np.isfinite(blocks[0]).all():
        return blocks
    text = data.decode("utf-8", errors="replace")
    text = text.replace("\r\n", "\n").replace("\r", "\n").replace("\\\n", " ")
    lines = [ln.split("#", 1)[0].strip() for ln in text.split("\n")]
    # Only whitespace-separated "v" / "f" records count ("vt", "vn", "vp", "fo"... do not).
    v_lines = [ln for ln in lines if ln[:2] in ("v ", "v\t")]
    if not v_lines:
        raise MeshFileError("no vertices ('v' lines) found")
    is_v = np.array([ln[:2] in ("v ", "v\t") for ln in lines], dtype=bool)
    is_f = np.array([ln[:2] in ("f ", "f\t") for ln in lines], dtype=bool)
    coords = [ln.split()[1:4] for ln in v_lines]
    if min(map(len, coords)) < 3:
        i = next(k for k, c in enumerate(coords) if len(c) < 3)
        lineno = int(np.flatnonzero(is_v)[i]) + 1
        raise MeshFileError(f"line {lineno}: vertex needs 3 coordinates",
                            details={"line": lineno})
    try:
        vertices = np.array(coords, dtype=np.float64)
    except ValueError:
        raise _not_a_number(["\t".join(c) for c in coords], np.flatnonzero(is_v), _FLOAT,
                            "vertex coordinate", "a number") from None
    if not np.isfinite(vertices).all():
        raise _non_finite(vertices, coords, np.flatnonzero(is_v))

    f_rows = np.flatnonzero(is_f)
    if f_rows.size == 0:
        return vertices, np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    # "f 1/2/3 4//5 6" -> "1 4 6": keep each entry's leading v index.
    f_text = _OBJ_REF_TAIL.sub("", "\n".join([lines[r][2:] for r in f_rows]))
    counts = np.fromiter(map(len, map(str.split, f_text.split("\n"))), dtype=np.int64,
                         count=f_rows.size)
    tokens = f_text.split()
    try:
        ids = np.array(tokens, dtype=np.int64)
    except ValueError:
        raise _not_a_number(f_text.split("\n"), f_rows, _INTEGER, "face index",
                            "a whole number") from None
    except OverflowError:
        raise _huge_index(tokens, np.repeat(f_rows, counts)) from None
    if counts.min() < 3:
        lineno = int(f_rows[np.argmax(counts < 3)]) + 1
        raise MeshFileError(f"line {lineno}: face with fewer than 3 vertices",
                            details={"line": lineno})
    # 1-based; negative indices count back from the last vertex defined before the face line.
    nv_before = np.cumsum(is_v)[f_rows]  # vertices defined up to each face line
    nv_tok = np.repeat(nv_before, counts)
    idx = np.where(ids > 0, ids - 1, np.where(ids < 0, nv_tok + ids, -1))
    bad = (idx < 0) | (idx >= nv_tok)
    if bad.any():
        k = int(np.argmax(bad))
        face = int(np.searchsorted(np.cumsum(counts), k, side="right"))
        raise _bad_index(int(ids[k]), face, int(f_rows[face]) + 1, int(nv_tok[k]))
    triangles, face_polygon = fan_triangulate(counts)
    return vertices, idx[triangles], face_polygon


def _obj_blocks(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """An OBJ file's ``v`` and ``f`` lines read as numpy blocks, or None when its layout needs
    the line-by-line parser of :func:`parse_obj`.

    Lines are classified by their first two bytes; the ``v`` lines are one block of at least
    three numbers each, the ``f`` lines (``/vt/vn`` tails dropped) one block of the same
    count of integers each (``np.loadtxt``). A comment after data, a line continuation, an
    indented line, a ragged or non-numeric block or an index outside the vertices defined
    before its line gives None: :func:`parse_obj` then reads the file or names the line at
    fault, so both accept the same files and give the same arrays.

    Args:
        data: The OBJ file.

    Returns:
        ``(vertices, faces, face_polygon)`` as :func:`parse_obj`, or None.
    """
    if b"\\\n" in data or b"\\\r" in data:
        return None
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    raw = np.frombuffer(data, np.uint8)
    starts = np.concatenate([[0], np.flatnonzero(raw == 10) + 1])
    hashes = np.flatnonzero(raw == ord("#"))
    if (raw[hashes[hashes > 0] - 1] != 10).any():  # a comment after data
        return None
    head, second = _byte_at(raw, starts), _byte_at(raw, starts + 1)
    if ((head == 32) | (head == 9)).any():  # indented lines
        return None
    gap = (second == 32) | (second == 9)
    is_v, is_f = gap & (head == ord("v")), gap & (head == ord("f"))
    v_rows, f_rows = np.flatnonzero(is_v), np.flatnonzero(is_f)
    if v_rows.size == 0 or f_rows.size == 0:
        return None
    line_bytes = np.diff(np.append(starts, len(raw)))  # each line with its newline
    vertices = number_block(raw[np.repeat(is_v, line_bytes)].tobytes(), np.float64,
                            v_rows.size, columns=(1, 2, 3))
    in_faces = np.repeat(is_f, line_bytes)
    in_faces[starts[f_rows]] = in_faces[starts[f_rows] + 1] = False  # the "f " of each line
    face_text = raw[in_faces].tobytes()
    if b"/" in face_text:
        face_text = _OBJ_REF_TAIL_BYTES.sub(b"", face_text)
    entries = number_block(face_text, np.int64, f_rows.size)
    if vertices is None or entries is None or entries.shape[1] < 3:
        return None
    # 1-based; negative indices count back from the last vertex defined before the face line.
    defined = np.cumsum(is_v)[f_rows][:, None]
    idx = np.where(entries > 0, entries - 1, np.where(entries < 0, defined + entries, -1))
    if ((idx < 0) | (idx >= defined)).any():
        return None
    triangles, polygon = fan_triangulate(np.full(f_rows.size, entries.shape[1], np.int64))
    return vertices, idx.ravel()[triangles], polygon


def _byte_at(raw: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(k,) uint8 the bytes of ``raw`` at ``positions``, a newline past its end."""
    inside = positions < len(raw)
    return np.where(inside, raw[np.where(inside, positions, 0)], 10).astype(np.uint8)


def _not_a_number(records: list[str], rows: np.ndarray, number: re.Pattern[str],
                  what: str, expected: str) -> MeshFileError:
    """The error for the first entry of ``records`` (one OBJ record's entries, whitespace
    separated, the record of file line ``rows[k] + 1`` each) that is not ``number``, naming
    its line and quoting it (numpy's own message names neither).

    Args:
        records: The records' entries as written, one string per record.
        rows: The 0-based line of each record.
        number: What an entry must match in full.
        what: What an entry is, in words ("face index").
        expected: What it should be, in words ("a whole number").

    Returns:
        The error to raise.
    """
    text = "\n".join(records)
    bad = next((m for m in _TOKEN.finditer(text) if not number.fullmatch(m[0])), None)
    if bad is None:
        return MeshFileError(f"a {what} is not {expected}")
    lineno = int(rows[text.count("\n", 0, bad.start())]) + 1
    return MeshFileError(f"line {lineno}: {what} {bad[0]!r} is not {expected}",
                         details={"line": lineno, "value": bad[0]})


def _bad_index(value: int, face: int, line: int, defined: int) -> MeshFileError:
    """The error for a face's vertex index that names no vertex defined before its line.

    Args:
        value: The index as written (1-based; negative: counted back from the last vertex).
        face: The face record at fault (0-based, in the file's order of ``f`` lines).
        line: Its file line (1-based).
        defined: The vertices defined before that line.

    Returns:
        The error to raise (``index`` the face, ``details`` its line and the value).

    Example:
        >>> _bad_index(9, 2, 7, 4).reason
        'line 7: face 2 has vertex index 9, but only 4 vertices are defined before its line'
    """
    if value == 0:
        why = ("0, but OBJ indices start at 1 (negative ones count back from the last vertex "
               "defined)")
    elif value > 0:
        why = f"{value}, but only {defined} vertices are defined before its line"
    else:
        why = (f"{value}, which counts back past the first vertex (only {defined} are "
               "defined before its line)")
    return MeshFileError(f"line {line}: face {face} has vertex index {why}", index=face,
                         details={"line": line, "value": value})


def _non_finite(vertices: np.ndarray, coords: list[list[str]], rows: np.ndarray
                ) -> MeshFileError:
    """The error for the first vertex with a NaN or infinite coordinate.

    Args:
        vertices: (n, 3) float64 the ``v`` lines' coordinates.
        coords: Those coordinates as written, 3 per ``v`` line.
        rows: (n,) int64 the 0-based file line of each ``v`` line.

    Returns:
        The error to raise (``index`` the vertex, ``details`` its line and the value).
    """
    vertex, column = (int(i) for i in np.argwhere(~np.isfinite(vertices))[0])
    line, value = int(rows[vertex]) + 1, coords[vertex][column]
    return MeshFileError(f"line {line}: vertex {vertex} has a non-finite coordinate "
                         f"{value!r}", index=vertex, details={"line": line, "value": value})


def _huge_index(tokens: list[str], token_rows: np.ndarray) -> MeshFileError:
    """The error for a face index beyond int64, naming its line and quoting the index.

    Args:
        tokens: The face entries' vertex indices, as written.
        token_rows: The line index of each token.

    Returns:
        The error to raise.
    """
    long = np.flatnonzero(np.fromiter(map(len, tokens), np.intp, len(tokens)) >= 19)
    limit = np.iinfo(np.int64)
    k = next(int(k) for k in long if not limit.min <= int(tokens[k]) <= limit.max)
    lineno = int(token_rows[k]) + 1
    return MeshFileError(f"line {lineno}: face index {tokens[k]} is far beyond the vertices "
                         "of the file", details={"line": lineno, "value": tokens[k]})
