"""Binary OFF (``OFF BINARY``), read with numpy: no Python loop over vertices or faces.

The layout (Geomview's ``OFF`` page; pmp-library writes it too): a text line
``[ST][C][N][4]OFF BINARY``, then 4-byte words: the vertex, face and edge counts (int32),
every vertex's floats (float32: x y z, then w with ``4``, a normal with ``N``, an RGBA colour
with ``C``, a texture coordinate with ``ST``), then every face as ``k i0 ... ik-1`` (int32),
in Geomview's layout followed by a colour count ``c`` and ``c`` float32 colour components.

Files differ in two ways this reader settles from the data itself:

* **Byte order**: Geomview writes big-endian; pmp-library before 3.0 wrote little-endian (its
  ``beetle.off`` and ``fairing-cross.off`` test files). The order whose counts fit the file
  is taken (pmp-library's rule), big-endian when both do.
* **Face colours**: with or without Geomview's colour count after each face's indices; the
  layout whose face records end exactly at the file's end is taken (without first).

Faces of one corner count are found with strides; faces of mixed counts by pointer doubling
over the words (:func:`~solver.mesh.mesh_readers._follow`), each face's successor being
``p + 1 + k`` (``+ 1 + c`` with colours).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final

import numpy as np

from ..core.errors import MeshFileError
from .mesh_readers import _follow, _ranges, fan_triangulate

_HEADER: Final = re.compile(rb"^\s*(ST)?(C)?(N)?(4)?(n)?OFF[ \t]+BINARY[^\n]*\n")
"""The text line before the binary data: the keyword's prefixes and ``BINARY``."""

HEADER_SCAN: Final = 256
"""Bytes :func:`is_binary_off` looks at for the header line."""

COLOUR_LIMIT: Final = 4
"""Most colour components a face may carry (Geomview: 0, 1 index, 3 RGB or 4 RGBA)."""


def is_binary_off(data: bytes) -> bool:
    """Whether ``data`` starts with a binary OFF header line (``OFF BINARY``, ``NOFF
    BINARY``, ...).

    Example:
        >>> is_binary_off(b"OFF BINARY\\n" + bytes(12)), is_binary_off(b"OFF\\n3 1 0\\n")
        (True, False)
    """
    return _HEADER.match(data[:HEADER_SCAN]) is not None


@dataclass(frozen=True)
class _Layout:
    """One reading of the words after the header: byte order and the face records' shape."""

    order: str  # ">" big-endian or "<" little-endian
    colours: bool  # each face's indices followed by a colour count and its colours


def parse_binary_off(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A binary OFF file as vertices and fan-triangulated faces.

    Args:
        data: The whole file.

    Returns:
        (n, 3) float64 vertices (homogeneous ones divided by w), (m, 3) int64 triangles and
        (m,) int64 the face record of each triangle.

    Raises:
        MeshFileError: No binary header, dimension ``n`` prefix, counts that do not fit the
            file, a face with fewer than 3 corners, face records that fit neither layout,
            a coordinate that is not finite.

    Example:
        >>> words = np.array([4, 1, 0], ">i4").tobytes() + np.array(
        ...     [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], ">f4").tobytes()
        >>> data = b"OFF BINARY\\n" + words + np.array([4, 0, 1, 2, 3, 0], ">i4").tobytes()
        >>> vertices, faces, polygon = parse_binary_off(data)
        >>> vertices.shape, faces.tolist(), polygon.tolist()
        ((4, 3), [[0, 1, 2], [0, 2, 3]], [0, 0])
    """
    header = _HEADER.match(data[:HEADER_SCAN])
    if header is None:
        raise MeshFileError("not a binary OFF file: the first line must be 'OFF BINARY'",
                            file_type="off")
    texture, colour, normal, homogeneous, dimension = header.groups()
    if dimension:
        raise MeshFileError("binary nOFF (vertices of another dimension than 3) is not "
                            "supported", file_type="off")
    floats = 3 + bool(homogeneous) + 3 * bool(normal) + 4 * bool(colour) + 2 * bool(texture)
    body = data[header.end():]
    usable = len(body) - len(body) % 4
    orders = [order for order in (">", "<") if _counts_fit(body, order, floats)]
    if not orders:
        raise MeshFileError(
            f"binary OFF: the counts do not fit the file ({len(body)} bytes after the header "
            f"line; read big-endian {_counts(body, '>')}, little-endian {_counts(body, '<')})",
            file_type="off")
    faces = None
    for layout in (_Layout(order, colours) for order in orders for colours in (False, True)):
        n_vertices, n_faces, _ = _counts(body, layout.order)
        words = np.frombuffer(body, dtype=layout.order + "i4", count=usable // 4,
                              offset=0)[3 + n_vertices * floats:]
        faces = _face_records(words, n_faces, layout.colours)
        if faces is not None:
            break
    if faces is None:
        raise MeshFileError(
            "binary OFF: the face records fit neither layout (k indices, or k indices, a "
            "colour count and colours, after each count k)", file_type="off")
    starts, corners = faces
    vertices = _vertices(body, layout.order, n_vertices, floats, bool(homogeneous))
    if len(corners) and corners.min() < 3:
        k = int(np.argmax(corners < 3))
        raise MeshFileError(f"binary OFF: face {k} has {int(corners[k])} corners, fewer than "
                            "3", file_type="off", index=k,
                            details={"value": int(corners[k])})
    indices = words[_ranges(starts + 1, corners)].astype(np.int64)
    triangles, polygon = fan_triangulate(corners)
    return vertices, indices[triangles].reshape(-1, 3), polygon


def _counts(body: bytes, order: str) -> tuple[int, int, int]:
    """The header's vertex, face and edge counts read in byte ``order`` (zeros when the file
    is shorter than them)."""
    if len(body) < 12:
        return 0, 0, 0
    n_vertices, n_faces, n_edges = np.frombuffer(body, dtype=order + "i4", count=3)
    return int(n_vertices), int(n_faces), int(n_edges)


def _counts_fit(body: bytes, order: str, floats: int) -> bool:
    """Whether the counts read in ``order`` are non-negative and leave room for the vertices
    and at least four words per face."""
    n_vertices, n_faces, n_edges = _counts(body, order)
    if min(n_vertices, n_faces, n_edges) < 0 or n_vertices < 1 or n_faces < 1:
        return False
    return 4 * (3 + n_vertices * floats + 4 * n_faces) <= len(body)


def _vertices(body: bytes, order: str, n_vertices: int, floats: int, homogeneous: bool
              ) -> np.ndarray:
    """(n, 3) float64 positions from the vertex records' float32 words."""
    block = np.frombuffer(body, dtype=order + "f4", count=n_vertices * floats,
                          offset=12).reshape(n_vertices, floats)
    vertices = block[:, :3].astype(np.float64)
    if homogeneous:
        with np.errstate(divide="ignore", invalid="ignore"):
            vertices /= block[:, 3:4].astype(np.float64)
    bad = ~np.isfinite(vertices)
    if bad.any():
        row = int(np.argmax(bad.any(axis=1)))
        raise MeshFileError(f"binary OFF: vertex {row} has a non-finite coordinate "
                            f"{vertices[row].tolist()}", file_type="off", index=row,
                            details={"value": vertices[row].tolist()})
    return vertices


def _face_records(words: np.ndarray, n_faces: int, colours: bool
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """Where each of ``n_faces`` face records starts in ``words`` ((w,) int32 from the
    first face) and its corner count, when the records end exactly at the words' end; else
    None.

    Returns:
        ``(starts, corners)``: (f,) int64 word offsets and (f,) int64 counts.
    """
    if not len(words):
        return None
    uniform = _uniform_records(words, n_faces, colours)
    if uniform is not None:
        return uniform
    size = len(words)
    span = np.asarray(words, dtype=np.int64)
    after = np.arange(size, dtype=np.int64) + 1 + np.clip(span, 0, size)
    if colours:
        inside = np.minimum(after, size - 1)
        tail = np.clip(span[inside], 0, COLOUR_LIMIT)
        after = np.where(after < size, after + 1 + tail, size + 1)
    after = np.minimum(after, size)
    starts = _follow(after, 0, n_faces + 1)
    if starts[n_faces] != size or (starts[:n_faces] >= size).any():
        return None
    starts, corners = starts[:n_faces], span[starts[:n_faces]]
    ends = starts + 1 + corners  # unclipped: a record running past the end does not fit
    if colours:
        if (ends >= size).any() or (span[np.minimum(ends, size - 1)] > COLOUR_LIMIT).any():
            return None
        ends = ends + 1 + span[ends]
    if (corners < 0).any() or not np.array_equal(ends, np.append(starts[1:], size)):
        return None
    return starts, corners


def _uniform_records(words: np.ndarray, n_faces: int, colours: bool
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """The records when every face has the first face's corner count (and colour count):
    one stride; None when they do not."""
    k = int(words[0])
    if k < 1 or k + 1 >= len(words):
        return None
    c = int(words[k + 1]) if colours else -1
    if colours and not 0 <= c <= COLOUR_LIMIT:
        return None
    stride = k + 1 + (c + 1 if colours else 0)
    if stride * n_faces != len(words):
        return None
    records = words.reshape(n_faces, stride)
    if (records[:, 0] != k).any() or (colours and (records[:, k + 1] != c).any()):
        return None
    return (np.arange(n_faces, dtype=np.int64) * stride,
            np.full(n_faces, k, dtype=np.int64))
