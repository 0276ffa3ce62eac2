"""The mesh file parsers behind :mod:`solver.mesh.formats`' readers: OFF parsed here (OBJ in
:mod:`solver.mesh.obj_reader`), PLY, STL, GLB and glTF through trimesh (no processing, the
file's vertex order kept), and what they share (text decoding, fan triangulation of polygons,
numeric blocks, STL's merge of identical corners). The rules per format are
:mod:`solver.mesh.io`'s docstring; every parser returns ``(vertices, faces, face_polygon)``:
(n, 3) float, (m, 3) int triangles and the file face of each triangle (None: one file face
per triangle).

OFF records over several lines. OFF is whitespace-delimited, and some writers spread a record
over lines (libigl-tutorial-data's ``inspired_mesh_quads_*.off``: ``4 1007`` then ``55``,
``1008``, ``0`` on lines of their own). The rule read here (Geomview's, where a face's colour
is the rest of its line, made strict): after the header every record -- ``x y z ...`` or
``k i0 ... ik-1 [colour]`` -- starts a line (blank and ``#`` comment lines skipped);

* when that line holds the whole record (3 numbers, or ``k + 1``), the record is that line
  and the line's further columns (normals, colours, a face colour ``r g b [a]``) are ignored;
* else the record runs on over the next lines and must end with the end of a line: a record
  over several lines carries no further columns, so a short face in a file of one record a
  line (``3 0 1`` then ``3 1 2 3``) is that face's fault, not a record that takes the next
  line's count as its index.

A file whose records are one a line is read as ever (numpy blocks when its faces all have one
width, :func:`_off_blocks`); every other file as a token stream (:func:`_off_records`, no
Python loop over records: pointer doubling finds where each starts). A malformed file is
named at its record: if no record before the fault spans lines, in the words of the line by
line :func:`~solver.mesh.file_diagnosis.off_problem` (as before), else in the words of the
token stream (``the file ends inside face 1837 (from line 9190, 5 numbers; truncated?)``).
"""

from __future__ import annotations

import codecs
import io
import re
import warnings
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from ..core.errors import MeshFileError
from .file_diagnosis import off_problem
from .strips import strip_triangles
from .weld import sorted_positions


def off_short(data: bytes, vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """The OFF record at fault when the parser read fewer vertices or faces than the file's
    header announces (trimesh drops a truncated last face silently); None otherwise."""
    header = re.match(rb"\s*\w*OFF\s+(\d+)\s+(\d+)", data)
    if header is None:
        return None
    if len(vertices) >= int(header[1]) and len(faces) >= int(header[2]):
        return None
    return off_problem(data)


def text_as_utf8(data: bytes, fmt: str) -> bytes:
    """The file with its text (all of OFF and ASCII STL, the PLY header) as UTF-8.

    Text mesh files are ASCII apart from comments and names, which are often Latin-1; trimesh
    decodes text as UTF-8 (and would reach for an optional charset detector otherwise). Bytes
    that are not UTF-8 are read as Latin-1, which maps every byte to one character, so the
    numbers are untouched. Binary parts (binary STL, a binary PLY body) are left as they are.
    """
    if fmt == "ply":
        end = data.find(b"end_header")
        return data if end < 0 else _latin1_to_utf8(data[:end]) + data[end:]
    if fmt == "off" or (fmt == "stl" and not _is_binary_stl(data)):
        return _latin1_to_utf8(data)
    return data


def without_bom(data: bytes) -> bytes:
    """A text file's bytes as UTF-8 without a byte-order mark: UTF-16 (big- or little-endian,
    by its mark: Windows tools write OBJ files so, assimp's ``box_UTF16BE.obj``) decoded,
    UTF-8's mark dropped; a file without a mark as it is.

    Example:
        >>> without_bom("v 1 2 3".encode("utf-16")), without_bom(codecs.BOM_UTF8 + b"OFF")
        (b'v 1 2 3', b'OFF')
    """
    if data.startswith((codecs.BOM_UTF16_BE, codecs.BOM_UTF16_LE)):
        return data.decode("utf-16", errors="replace").encode("utf-8")
    if data.startswith(codecs.BOM_UTF8):
        return data[len(codecs.BOM_UTF8):]
    return data


def ascii_stl_text(data: bytes) -> bytes:
    r"""An ASCII STL without what comes before its ``solid`` keyword (blank lines, a
    byte-order mark; UTF-16 decoded by its mark); a binary STL (its size is its triangle
    count's) or any other data as it is.

    Example:
        >>> ascii_stl_text(b"\n  solid x\nendsolid x\n")
        b'solid x\nendsolid x\n'
    """
    if _is_binary_stl(data):
        return data
    text = without_bom(data).lstrip()
    return text if text[:5].lower() == b"solid" else data


def _latin1_to_utf8(text: bytes) -> bytes:
    try:
        text.decode("utf-8")
    except UnicodeDecodeError:
        return text.decode("latin-1").encode("utf-8")
    return text


def _is_binary_stl(data: bytes) -> bool:
    """A binary STL: an 80-byte header, a uint32 count n, then exactly n 50-byte records."""
    if len(data) < 84:
        return False
    count = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    return len(data) == 84 + 50 * count


def fan_triangulate(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangulation of polygons stored back to back, vectorized.

    Polygon j with k_j corners at token offsets ``o .. o + k_j - 1`` gives the triangles
    ``(o, o + t, o + t + 1)`` for t = 1 .. k_j - 2 (a triangle stays itself).

    Args:
        counts: (p,) int64 corners of each polygon, each >= 3.

    Returns:
        ``(triangles, polygon)``: (m, 3) int64 token offsets and (m,) int64 the polygon of
        each triangle, m = sum(counts - 2).

    Example:
        >>> import numpy as np
        >>> triangles, polygon = fan_triangulate(np.array([4, 3]))
        >>> triangles.tolist(), polygon.tolist()
        ([[0, 1, 2], [0, 2, 3], [4, 5, 6]], [0, 0, 1])
    """
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    ntri = counts - 2
    first = np.repeat(starts, ntri)
    t = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    polygon = np.repeat(np.arange(len(counts), dtype=np.int64), ntri)
    return np.stack([first, first + t, first + t + 1], axis=1), polygon


def load_trimesh(data: bytes, fmt: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """PLY/STL/GLB/glTF through trimesh without any processing or reordering; a PLY's
    polygon faces are triangulated here (:func:`_ply_polygons`)."""
    import trimesh  # deferred: heavy import, and only needed for these formats

    loaded = trimesh.load(io.BytesIO(data), file_type=fmt, process=False,
                          maintain_order=True)
    if isinstance(loaded, trimesh.Scene):
        return (*_single_scene_mesh(loaded, fmt), None)
    if fmt == "ply" and isinstance(loaded, trimesh.PointCloud):
        strips = _ply_strips(loaded.metadata)
        if strips is not None:
            return (np.asarray(loaded.vertices), *strips)
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshFileError(f"no triangle faces (file holds a {type(loaded).__name__})",
                            file_type=fmt)
    if fmt == "ply":
        polygons = _ply_polygons(loaded.metadata)
        if polygons is not None:
            return (np.asarray(loaded.vertices), *polygons)
    return np.asarray(loaded.vertices), np.asarray(loaded.faces), None


def _ply_strips(metadata: dict[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """The triangles of a PLY file's ``tristrips`` element (:func:`strip_triangles`: ``-1``
    restarts a strip, every second triangle flipped, the joins' repeated-index triangles
    dropped) and the strip each comes from, or None when the file has no strips."""
    element = (metadata.get("_ply_raw") or {}).get("tristrips") or {}
    data = element.get("data")
    if data is None:
        return None
    names = data.dtype.names or () if isinstance(data, np.ndarray) else tuple(data)
    if "vertex_indices" not in names:
        return None
    rows = data["vertex_indices"]  # ASCII: a dict of lists; binary: a record array
    if isinstance(rows, np.ndarray) and rows.dtype.names:  # binary: (count, indices)
        rows = rows[rows.dtype.names[-1]]
    if isinstance(rows, np.ndarray) and rows.dtype != object:  # one length: one block
        block = rows.astype(np.int64).reshape(len(rows), -1)
        indices = np.hstack([block, np.full((len(block), 1), -1)]).ravel()
    else:  # records of different lengths (ASCII): joined, each ended by -1
        counts = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
        flat = np.concatenate(rows).astype(np.int64) if len(rows) else np.zeros(0, np.int64)
        indices = np.insert(flat, np.cumsum(counts), -1)
    triangles, strip = strip_triangles(indices)
    if not len(triangles):
        raise MeshFileError("its triangle strips hold no triangle", file_type="ply")
    return triangles, strip


def _ply_polygons(metadata: dict[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """The PLY file's own face list, fan-triangulated (:func:`fan_triangulate`), or None
    when the file has no face list or only triangles (trimesh's faces are then the file's).

    trimesh triangulates polygons itself, but reorders the faces (triangles first) and
    splits quads differently from larger polygons; the raw list it keeps is used instead.
    """
    face = (metadata.get("_ply_raw") or {}).get("face") or {}
    data = face.get("data")
    if data is None:
        return None
    names = data.dtype.names or () if isinstance(data, np.ndarray) else tuple(data)
    lists = [data[name] for name in ("vertex_indices", "vertex_index") if name in names]
    if not lists:
        return None
    raw = lists[0]
    if isinstance(raw, np.ndarray) and raw.dtype.names:  # binary: (count, indices) records
        raw = raw[raw.dtype.names[-1]]
    if isinstance(raw, np.ndarray) and raw.dtype != object:
        rows = raw.reshape(len(raw), -1)
        if rows.shape[1] == 3:
            return None
        counts = np.full(len(rows), rows.shape[1], dtype=np.int64)
        tokens = rows.ravel()
    else:
        polygons = [np.asarray(row).ravel() for row in raw]
        counts = np.fromiter(map(len, polygons), dtype=np.int64, count=len(polygons))
        if (counts == 3).all():
            return None
        tokens = np.concatenate(polygons) if polygons else np.zeros(0, dtype=np.int64)
    if len(counts) and counts.min() < 3:
        k = int(np.argmax(counts < 3))
        raise MeshFileError(f"face {k} has fewer than 3 vertices", index=k)
    triangles, polygon = fan_triangulate(counts)
    return tokens.astype(np.int64)[triangles], polygon


def parse_off(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An OFF file (``OFF``, ``COFF``, ``NOFF``, ``CNOFF``... text header).

    Vertex records keep their first three numbers (colours and normals are ignored); a face
    record ``k i0 ... ik-1 [colour]`` is fan-triangulated (:func:`fan_triangulate`). A record
    may run over several lines (:func:`_off_records` states the rule). A file whose records
    are one per line and whose faces all have the same width is read in two numpy blocks
    (:func:`_off_blocks`, ~5x faster at a million faces); any other file, and every
    malformed one, by :func:`_off_records` (the errors name the record at fault).

    Args:
        data: The OFF file, UTF-8.

    Returns:
        (n, 3) float64 vertices, (m, 3) int64 triangles and (m,) int64 the face record of
        each triangle.
    """
    blocks = _off_blocks(data)
    if blocks is not None and np.isfinite(blocks[0]).all():
        return blocks
    return _off_records(data)


_WHITESPACE: Final = np.isin(np.arange(256), list(b" \t\n\v\f\r"))
"""(256,) bool: the bytes that separate an OFF file's tokens."""


@dataclass(frozen=True)
class _Tokens:
    """The whitespace-separated tokens of a text file, comments (``#`` to the line's end)
    left out, found with numpy (no Python loop over lines or tokens).

    Attributes:
        raw: (b,) uint8 the file, with a space for every comment byte and one more at the end.
        start: (t,) int64 the byte where each token starts.
        end: (t,) int64 the byte after its last.
        line: (t,) int64 the 0-based file line of each token.
        first: (d,) int64 the first token of each line holding one (a "data line").
        count: (d,) int64 the tokens on each data line.
        data_line: (t,) int64 the data line of each token.
    """

    raw: np.ndarray
    start: np.ndarray
    end: np.ndarray
    line: np.ndarray
    first: np.ndarray
    count: np.ndarray
    data_line: np.ndarray

    @classmethod
    def of(cls, data: bytes) -> _Tokens:
        """The tokens of ``data`` (newlines ``\\n``)."""
        raw = np.frombuffer(data + b" ", np.uint8)
        if b"#" in data:
            raw = _blank_comments(raw)
        space = _WHITESPACE[raw].view(np.int8)
        edge = np.diff(space, prepend=np.int8(1))  # -1 where a token starts, 1 after it
        starts = edge == -1
        start, end = np.flatnonzero(starts), np.flatnonzero(edge == 1)
        events = np.flatnonzero(starts | (raw == 10))  # token starts and newlines, in order
        newline = raw[events] == 10
        line = np.cumsum(newline)[~newline]
        is_first = np.diff(line, prepend=-1) != 0
        first = np.flatnonzero(is_first)
        return cls(raw, start, end, line, first, np.diff(np.append(first, len(start))),
                   np.cumsum(is_first) - 1)

    def text(self, k: int) -> str:
        """Token ``k`` as written."""
        return self.raw[self.start[k]:self.end[k]].tobytes().decode("utf-8", "replace")

    def whole_numbers(self, tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tokens read as whole numbers, vectorized (``[+-]digits``; more than 18 digits:
        +-(2**63 - 1), outside every index range).

        Args:
            tokens: (k,) int64 token numbers.

        Returns:
            ``(values, ok)``: (k,) int64 and (k,) bool whether each token is a whole number.
        """
        start, end = self.start[tokens], self.end[tokens]
        lead = self.raw[start]
        first = start + ((lead == ord("+")) | (lead == ord("-")))
        digits = end - first
        values, bad = np.zeros(len(tokens), dtype=np.int64), digits < 1
        last = len(self.raw) - 1
        for place in range(min(int(digits.max(initial=0)), 18)):  # digit by digit
            live = digits > place
            byte = self.raw[np.minimum(first + place, last)]
            bad |= live & ((byte < ord("0")) | (byte > ord("9")))
            values = np.where(live, values * 10 + (byte.astype(np.int64) - ord("0")), values)
        long = np.flatnonzero(digits > 18)
        if len(long):  # beyond every index; its further digits checked too
            values[long] = np.iinfo(np.int64).max
            tail = self.raw[_ranges(first[long] + 18, digits[long] - 18)]
            owner = np.repeat(np.arange(len(long)), digits[long] - 18)
            bad[long] |= np.bincount(owner, weights=(tail < ord("0")) | (tail > ord("9")),
                                     minlength=len(long)) > 0
        return np.where(lead == ord("-"), -values, values), ~bad


def _blank_comments(raw: np.ndarray) -> np.ndarray:
    """(b,) uint8 ``raw`` with every byte from a ``#`` to the end of its line a space."""
    hashes = np.flatnonzero(raw == ord("#"))
    newlines = np.append(np.flatnonzero(raw == 10), len(raw))
    stops = newlines[np.searchsorted(newlines, hashes)]
    first = np.unique(stops, return_index=True)[1]  # the first # of each line
    marks = np.zeros(len(raw) + 1, dtype=np.int8)
    marks[hashes[first]] = 1
    marks[stops[first]] = -1
    blanked = raw.copy()
    blanked[np.cumsum(marks[:-1], dtype=np.int8).astype(bool)] = ord(" ")
    return blanked


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The integers ``starts[j] .. starts[j] + lengths[j] - 1`` of every j, concatenated."""
    lengths = np.asarray(lengths, dtype=np.int64)
    offsets = np.cumsum(lengths) - lengths
    return np.repeat(np.asarray(starts, dtype=np.int64) - offsets, lengths) + np.arange(
        int(lengths.sum()), dtype=np.int64)


def _off_records(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An OFF file read as a stream of tokens, each record starting a line (the module's
    rule: a record on one line may carry further columns, a record over several lines ends
    with its last line), vectorized throughout (:func:`_record_lines`).

    Args:
        data: The OFF file, UTF-8.

    Returns:
        ``(vertices, faces, face_polygon)`` as :func:`parse_off`.

    Raises:
        MeshFileError: Naming the record at fault. In a file whose records are one per line
            up to the fault the error carries no file type, so that
            :func:`solver.mesh.io.read_mesh` words it as :func:`off_problem` reads the file
            line by line; in a file with records over several lines it says what the
            token stream found.
    """
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    tokens = _Tokens.of(data)
    n_vertices, n_faces, used = _off_header(
        [_words(tokens, d) for d in range(min(2, len(tokens.first)))])
    if n_vertices < 0 or n_faces < 0:
        raise MeshFileError(f"cannot parse OFF data: the header's counts ({n_vertices} "
                            f"vertices, {n_faces} faces) must not be negative",
                            file_type="off")
    lines = len(tokens.first)
    three = np.full(lines, 3, dtype=np.int64)
    vertex_lines = _record_lines(tokens, three, used, n_vertices)
    spans = _check_complete(tokens, three, vertex_lines, n_vertices, "vertex", False)
    counts, whole = tokens.whole_numbers(tokens.first)
    total = len(tokens.start)  # a count beyond the tokens: a record the file ends inside
    need = np.where(whole, np.clip(counts, 0, total) + 1, -1)
    face_lines = _record_lines(tokens, need, int(vertex_lines[-1]), n_faces)
    spans = _check_complete(tokens, need, face_lines, n_faces, "face", spans)
    vertices = _off_vertices(tokens, vertex_lines[:-1], spans)
    faces, polygon = _off_faces(tokens, face_lines[:-1], counts[face_lines[:-1]], spans)
    return vertices, faces, polygon


def _words(tokens: _Tokens, line: int) -> list[str]:
    """The first (at most 8) tokens of data line ``line``, as text."""
    first = int(tokens.first[line])
    return [tokens.text(k) for k in range(first, first + min(int(tokens.count[line]), 8))]


def _record_lines(tokens: _Tokens, need: np.ndarray, start: int, n: int) -> np.ndarray:
    """The data lines where ``n`` records start, the first at data line ``start``.

    A record starting at data line d takes ``need[d]`` tokens: those of its line when the
    line holds as many (the line's further tokens are ignored), else the tokens of the next
    lines up to the end of a line holding its last one. The next record starts on the next
    data line. Followed by pointer doubling (:func:`_follow`) unless every record is on its
    own line.

    Args:
        tokens: The file's tokens.
        need: (d,) int64 the tokens a record starting at each data line takes; < 1: that
            line cannot start one (its count is not a whole number).
        start: The data line of record 0.
        n: The records.

    Returns:
        (n + 1,) int64 the data line of each record and of the line after the last one;
        ``d`` (the data lines) after a record that does not end as the rule says. Fewer
        when the file has fewer lines than records (the last one ``d``).
    """
    lines = len(tokens.first)
    n = min(n, max(lines - start, 0))  # each takes a line at least: the rest are missing
    if (tokens.count >= need)[start:start + n].all() and (
            need[start:start + n] >= 1).all():
        return np.arange(start, start + n + 1, dtype=np.int64)
    every = np.arange(lines)
    fits, end_line = _record_fit(tokens, need, every)
    return _follow(np.where(fits, end_line + 1, lines), start, n + 1)


def _record_fit(tokens: _Tokens, need: np.ndarray, lines: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Whether records starting at data ``lines`` ((k,) int64) end as the rule of
    :func:`_record_lines` says, and the data line each ends on.

    Returns:
        ``(fits, end_line)``: (k,) bool and (k,) int64 (meaningless where it does not fit).
    """
    want = need[lines]
    one_line = (want >= 1) & (tokens.count[lines] >= want)
    last = tokens.first[lines] + want - 1
    inside = (want >= 1) & (last < len(tokens.start))
    end_line = tokens.data_line[np.where(inside, last, 0)]
    closes = last + 1 == tokens.first[end_line] + tokens.count[end_line]  # ends its line
    return one_line | (inside & closes), np.where(one_line, lines, end_line)


def _follow(after: np.ndarray, start: int, steps: int) -> np.ndarray:
    """``start``, ``after[start]``, ``after[after[start]]``, ... (``steps`` of them) by
    pointer doubling: log2(steps) vectorized gathers instead of a loop over the records.

    Args:
        after: (d,) int64 the data line after each, greater than it; ``d`` past the end.
        start: Where to start, <= d.
        steps: How many lines to list.

    Returns:
        (steps,) int64 the lines; ``d`` once past the end.

    Example:
        >>> _follow(np.array([2, 3, 3, 5, 5]), 0, 4).tolist()
        [0, 2, 3, 5]
    """
    jump = np.append(after, len(after))[start:] - start  # past the end stays there
    position = np.zeros(steps, dtype=np.int64)
    step = np.arange(steps)
    bit = 1
    while bit < steps:
        take = (step & bit) != 0
        position[take] = jump[position[take]]
        jump = jump[jump]
        bit <<= 1
    return position + start


def _first_fault(tokens: _Tokens, need: np.ndarray, lines: np.ndarray, n: int
                 ) -> tuple[int | None, bool]:
    """The first of ``n`` records at ``lines`` (:func:`_record_lines`) that the file does
    not hold or that does not end as the rule says, and whether a record read whole before
    it runs over several lines.

    Returns:
        ``(record, spans)``: record None when all ``n`` are whole.
    """
    held = lines[:n] < len(tokens.first)
    count = int(np.argmin(held)) if not held.all() else len(held)
    fits, _ = _record_fit(tokens, need, lines[:count])
    fault = int(np.argmin(fits)) if not fits.all() else (count if count < n else None)
    whole = lines[:n if fault is None else fault]
    return fault, bool((tokens.count[whole] < need[whole]).any())


def _check_complete(tokens: _Tokens, need: np.ndarray, lines: np.ndarray, n: int,
                    what: str, spans: bool) -> bool:
    """Whether a record of ``n`` at ``lines`` runs over several lines (or ``spans``); raise
    when the file does not hold them, naming the record at fault and its line."""
    fault, spanned = _first_fault(tokens, need, lines, n)
    spans = spans or spanned
    if fault is None:
        return spans
    line = int(lines[fault])
    if line >= len(tokens.first):
        raise _off_error(f"the file ends after {fault} of the {n} {_plural(what)} its "
                         "header announces (truncated?)", spans)
    where = int(tokens.line[tokens.first[line]]) + 1
    if need[line] < 1:
        word = tokens.text(int(tokens.first[line]))
        raise _off_error(f"line {where}: {what} {fault} starts with {word!r}, not a "
                         "whole number of corners", spans, index=fault)
    last = int(tokens.first[line] + need[line] - 1)
    if last >= len(tokens.start):
        raise _off_error(f"the file ends inside {what} {fault} (from line {where}, "
                         f"{need[line]} numbers; truncated?)", spans, index=fault)
    stop = int(tokens.line[last]) + 1
    raise _off_error(
        f"line {stop}: {what} {fault} (from line {where}, {need[line]} numbers) ends "
        f"before this line does ({tokens.text(last + 1)!r} follows): a record over "
        "several lines must end with its last line, further columns (a colour) follow "
        "only a record on one line", spans, index=fault)


def _plural(what: str) -> str:
    return "vertices" if what == "vertex" else what + "s"


def _off_error(reason: str, spans: bool, index: int | None = None,
               details: dict[str, Any] | None = None) -> MeshFileError:
    """The error of a malformed OFF record: with the file type (its words stand) in a file
    with records over several lines, else without (:func:`solver.mesh.io.read_mesh` then
    words it as :func:`off_problem`, line by line, as ever)."""
    if spans:
        return MeshFileError(f"cannot parse OFF data: {reason}", file_type="off",
                             index=index, details=details)
    return MeshFileError(reason, index=index, details=details)


def _off_vertices(tokens: _Tokens, lines: np.ndarray, spans: bool) -> np.ndarray:
    """(n, 3) float64 the first three numbers of the vertex records at data ``lines``;
    raises naming a coordinate that is not a finite number."""
    if not len(lines):
        return np.zeros((0, 3), dtype=np.float64)
    which = tokens.first[lines][:, None] + np.arange(3)
    if (tokens.count[lines] >= 3).all():  # one per line: the lines' bytes
        end = tokens.first[lines[-1]] + tokens.count[lines[-1]] - 1
        text = tokens.raw[tokens.start[which[0, 0]]:tokens.end[end]].tobytes()
        vertices = number_block(text, np.float64, len(lines), columns=(0, 1, 2))
    else:
        vertices = number_block(_number_text(tokens, which), np.float64, len(lines))
    if vertices is None:
        for k in which.ravel():  # the error's words only: the first that is not a number
            try:
                float(tokens.text(int(k)))
            except ValueError:
                row = int(np.argmax((which == k).any(axis=1)))
                raise _off_error(f"line {tokens.line[k] + 1}: vertex {row} has a coordinate "
                                 f"that is not a number: {tokens.text(int(k))!r}", spans,
                                 index=row) from None
        raise _off_error("a vertex coordinate is not a number", spans)
    vertices = vertices.reshape(len(lines), 3)
    bad = ~np.isfinite(vertices)
    if bad.any():
        row, column = (int(i) for i in np.argwhere(bad)[0])
        k = int(which[row, column])
        value, line = tokens.text(k), int(tokens.line[k]) + 1
        raise MeshFileError(f"line {line}: vertex {row} has a non-finite coordinate "
                            f"{value!r}", file_type="off", index=row,
                            details={"line": line, "value": value})
    return vertices


def _number_text(tokens: _Tokens, which: np.ndarray) -> bytes:
    """The tokens ``which`` ((r, c) int64) as text, a row of them per line."""
    start = tokens.start[which.ravel()]
    length = tokens.end[which.ravel()] - start
    text = tokens.raw[_ranges(start, length + 1)]  # each token and the byte after it
    gaps = np.cumsum(length + 1) - 1
    text[gaps] = ord(" ")
    text[gaps[which.shape[1] - 1::which.shape[1]]] = ord("\n")
    return text.tobytes()


def _off_faces(tokens: _Tokens, lines: np.ndarray, corners: np.ndarray, spans: bool
               ) -> tuple[np.ndarray, np.ndarray]:
    """The face records at data ``lines`` with ``corners`` ((f,) int64) each,
    fan-triangulated: (m, 3) int64 triangles and (m,) int64 the face of each."""
    if not len(corners):
        return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    if len(corners) and corners.min() < 3:
        k = int(np.argmax(corners < 3))
        line = int(tokens.line[tokens.first[lines[k]]]) + 1
        reason = f"face {k} has fewer than 3 vertices"
        raise _off_error(f"line {line}: {reason}" if spans else reason, spans, index=k)
    which = _ranges(tokens.first[lines] + 1, corners)
    indices, whole = tokens.whole_numbers(which)
    if not whole.all():
        bad = int(np.argmin(whole))
        face = int(np.searchsorted(np.cumsum(corners), bad, side="right"))
        line, word = int(tokens.line[which[bad]]) + 1, tokens.text(int(which[bad]))
        raise _off_error(f"line {line}: face {face} has a vertex index that is not a whole "
                         f"number: {word!r}", spans, index=face,
                         details={"line": line, "value": word})
    triangles, polygon = fan_triangulate(corners)
    return indices[triangles].reshape(-1, 3), polygon


def _off_header(records: list[list[str]]) -> tuple[int, int, int]:
    """The vertex and face counts of an OFF file from its first records.

    Args:
        records: The tokens of its first two records (lines with data), or fewer.

    Returns:
        ``(n_vertices, n_faces, used)``: ``used`` records (1 or 2) make the header.

    Raises:
        MeshFileError: No ``OFF`` keyword, binary OFF, or no counts.
    """
    if not records or not re.match(r"^[A-Za-z]*OFF", records[0][0]):
        raise MeshFileError("not an OFF file: the first line must be OFF")
    glued = re.match(r"^([A-Za-z]*OFF)(\S+)$", records[0][0])  # "OFF8 6 12": counts glued on
    header = [glued.group(1), glued.group(2), *records[0][1:]] if glued else records[0]
    if any(word.upper() == "BINARY" for word in header[1:]):
        raise MeshFileError("'BINARY' must follow the OFF keyword on the file's first line")
    used = 1 if len(header) >= 3 else 2
    counts_line = header[1:] if used == 1 else (records[1] if len(records) > 1 else [])
    try:
        return int(counts_line[0]), int(counts_line[1]), used
    except (IndexError, ValueError):
        raise MeshFileError("the OFF header needs the vertex and face counts") from None


OFF_HEADER_SCAN: Final = 64
"""Lines :func:`_off_blocks` looks through for the header's records (comments, blanks)."""


def _off_blocks(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """An OFF file read as two numpy blocks, or None when its layout needs the record-by-record
    parser of :func:`parse_off`.

    The header's records are found line by line; then the next ``n_vertices`` lines must be
    the vertex records and the ``n_faces`` after them the face records, each block of one
    width (``np.loadtxt``), every face with the same corner count ``k`` and at least ``k + 1``
    integers (further columns are a colour). A blank or comment line among them, a ragged or
    non-numeric block, or a short file gives None: the other parser then reads it or names
    the record at fault, so both accept the same files and give the same arrays.

    Args:
        data: The OFF file, UTF-8.

    Returns:
        ``(vertices, faces, face_polygon)`` as :func:`parse_off`, or None.
    """
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    records: list[list[str]] = []
    start = 0
    for _ in range(OFF_HEADER_SCAN):
        end = data.find(b"\n", start)
        end = len(data) if end < 0 else end
        tokens = data[start:end].split(b"#", 1)[0].decode("utf-8", "replace").split()
        start = end + 1
        if tokens:
            records.append(tokens)
            try:
                n_vertices, n_faces, used = _off_header(records)
            except MeshFileError:  # the counts on the next record, or a bad header
                if len(records) == 1:
                    continue
                return None  # parse_off names the problem
            if used == len(records):
                break
        if start > len(data):
            return None
    else:
        return None
    if n_vertices < 1 or n_faces < 1:
        return None
    newlines = np.flatnonzero(np.frombuffer(data, np.uint8, offset=start) == 10) + start
    if len(newlines) < n_vertices + n_faces - 1:
        return None
    ends = np.append(newlines, len(data))
    vertex_end, face_end = int(ends[n_vertices - 1]), int(ends[n_vertices + n_faces - 1])
    faces = number_block(data[vertex_end + 1:face_end], np.int64, n_faces)
    if faces is None:  # first: a file of mixed polygons is told early
        return None
    vertices = number_block(data[start:vertex_end], np.float64, n_vertices)
    if vertices is None or vertices.shape[1] < 3:
        return None
    k = int(faces[0, 0])
    if k < 3 or faces.shape[1] < k + 1 or (faces[:, 0] != k).any():
        return None
    triangles, polygon = fan_triangulate(np.full(n_faces, k, dtype=np.int64))
    return (np.ascontiguousarray(vertices[:, :3]), faces[:, 1:k + 1].ravel()[triangles],
            polygon)


def number_block(text: bytes, dtype: type, rows: int,
                 columns: tuple[int, ...] | None = None) -> np.ndarray | None:
    """``rows`` lines of numbers of one width as a (rows, width) array (``np.loadtxt``; ``#``
    starts a comment), or only ``columns`` of lines at least that wide; None when the block
    is ragged, holds something else or has a line without numbers (then it would not be
    ``rows`` rows)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # loadtxt warns about empty input
            block = np.loadtxt(io.BytesIO(text), dtype=dtype, comments="#", ndmin=2,
                               encoding="latin-1", usecols=columns)
    except (ValueError, OverflowError):
        return None
    return block if block.shape[0] == rows else None


def _single_scene_mesh(scene: Any, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    """The triangle meshes of a scene (glTF, multi-solid STL), each instance with its node
    transform applied, concatenated in the scene graph's node order (each primitive's
    vertices in its own order). The parts keep their places: the forms carry each
    component's placement (:mod:`solver.mesh.placement`)."""
    import trimesh

    meshes = {name: g for name, g in scene.geometry.items() if isinstance(g, trimesh.Trimesh)}
    if not meshes:
        raise MeshFileError("no triangle mesh found in the data (points and lines are not "
                            "read)", file_type=fmt)
    instances = [node for node in scene.graph.nodes_geometry
                 if scene.graph[node][1] in meshes] or [None]
    vertices, faces, offset = [], [], 0
    for node in instances:
        if node is None:  # no node: the one mesh as stored
            name, transform = next(iter(meshes)), np.eye(4)
        else:
            transform, name = scene.graph[node]
        mesh = meshes[name]
        part = np.asarray(mesh.vertices, dtype=np.float64)
        transform = np.asarray(transform, dtype=np.float64)
        if not np.array_equal(transform, np.eye(4)):
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                homog = np.hstack([part, np.ones((part.shape[0], 1))]) @ transform.T
                part = homog[:, :3] / homog[:, 3:4]  # non-finite: named by the caller
        vertices.append(part)
        faces.append(np.asarray(mesh.faces, dtype=np.int64) + offset)
        offset += len(part)
    return np.concatenate(vertices), np.concatenate(faces)


def merge_identical(vertices: np.ndarray, faces: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical positions; new vertices numbered by first occurrence.

    The positions are sorted by a hash of their bits (one stable argsort: ~5x faster than
    ``np.unique(axis=0)`` at a million faces); when two different positions share a hash
    they are sorted by their coordinates instead (:func:`solver.mesh.weld.sorted_positions`).

    Args:
        vertices: (k, 3) float positions.
        faces: (m, 3) int indices into ``vertices``.

    Returns:
        (n, 3) float64 unique positions and (m, 3) int64 faces into them.

    Example:
        >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 1, 0.]])
        >>> merged, faces = merge_identical(v, np.array([[0, 1, 3], [2, 3, 1]]))
        >>> merged.tolist(), faces.tolist()
        ([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [[0, 1, 2], [0, 2, 1]])
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64) + 0.0  # + 0.0: -0.0 becomes 0.0
    if v.shape[0] == 0:
        return v.reshape(0, 3), np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    order, same = sorted_positions(v)
    starts = np.concatenate([[True], ~same])
    group = np.cumsum(starts) - 1  # the group of each position, in sorted order
    first = order[starts]  # stable sorts: a group's first member is its first occurrence
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    new_index = np.empty(len(v), dtype=np.int64)
    new_index[order] = rank[group]  # old vertex -> merged vertex
    return v[np.sort(first)], new_index[np.asarray(faces, dtype=np.int64)]
