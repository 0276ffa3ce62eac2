"""Mesh file input/output: OBJ, OFF, PLY, STL, GLB (and embedded-buffer glTF) <-> arrays.

Loading keeps the file's vertex order and count: vertex ``i`` of the result is the ``i``-th
vertex record of the file, including vertices that no face references (those matter: the
solver's inputs are indexed by vertex). The one exception is STL, which stores each triangle
with its own three corners: exactly equal positions are merged so the mesh is connected, and
the merged vertices are numbered in order of first occurrence.

Per format:

* **OBJ** -- parsed here, not by trimesh: trimesh splits vertices on faces with ``vt``/``vn``
  indices (one vertex per unique ``v/vt/vn`` triple, creating false boundaries), drops
  unreferenced ``v`` lines unless ``maintain_order`` is set, and gives every ``usemtl``/``o``
  group its own vertex set. Here every ``v`` line is one vertex; ``f`` entries use only their
  ``v`` index (``v``, ``v/vt``, ``v//vn``, ``v/vt/vn``; negative = relative), polygons are
  fan-triangulated, and all groups/objects/materials are merged in file order. ``vt``, ``vn``,
  ``l``, ``p``, materials and vertex colours are ignored.
* **OFF** -- parsed here (``OFF``/``COFF``/``NOFF`` text headers; extra vertex columns and
  face colours are ignored).
* **PLY** -- trimesh (``process=False``); polygon faces are read back from the file's face
  list and triangulated here.
* **Polygons** -- in OBJ, OFF and PLY a face with k > 3 corners ``(v0, ..., vk-1)`` is
  fan-triangulated into the k - 2 triangles ``(v0, vj, vj+1)``, j = 1 .. k - 2, in file order
  (the same rule in every format; :func:`read_mesh` reports how many faces were polygons and
  which file face each triangle comes from). Answers are given on these triangles.
* **STL** -- trimesh, then merge of bit-identical positions (``-0.0`` equals ``0.0``).
* **GLB** / **glTF** (``.gltf`` only with ``data:`` URI buffers) -- trimesh. Every triangle
  mesh primitive of every node instance is taken with its node transform applied (skipped
  when it is the identity, so positions are bit-exact), concatenated in the scene graph's node
  order: the parts of a multi-part model are components of one mesh, and the forms keep each
  component's placement (:mod:`solver.placement`). A multi-solid ASCII STL is read the same
  way (then merged). Points and lines are ignored.

Saving (:func:`save_mesh`): OBJ, OFF and PLY are written here with full float64 precision
(``%.17g`` text, binary little-endian ``double`` PLY) so a save/load round trip is exact; STL
(float32, unshared vertices) and GLB (float32) go through trimesh.

All parse failures raise :class:`~solver.errors.MeshFileError` (a
:class:`~solver.errors.SolverInputError`) with a ``reason``; unknown formats raise its subclass
:class:`~solver.errors.UnsupportedFormatError`. The HTTP service answers them 400
``unreadable-file`` and 415 ``unsupported-file-type``.
"""

from __future__ import annotations

import io
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import (
    IndexOutOfRangeError,
    MeshFileError,
    NonFiniteValueError,
    ShapeMismatchError,
    UnsupportedFormatError,
)
from .file_diagnosis import off_problem

__all__ = [
    "LOAD_FORMATS",
    "SAVE_FORMATS",
    "LoadedMesh",
    "MeshFileError",
    "UnsupportedFormatError",
    "load_mesh",
    "load_mesh_file",
    "read_mesh",
    "resolve_format",
    "save_mesh",
]

LOAD_FORMATS: Final = ("obj", "off", "ply", "stl", "glb", "gltf")
"""Formats :func:`load_mesh` reads (lower-case names / file extensions)."""
SAVE_FORMATS: Final = ("obj", "off", "ply", "stl", "glb")
"""Formats :func:`save_mesh` writes."""

_ALIASES: Final[dict[str, str]] = {
    "model/obj": "obj",
    "model/stl": "stl",
    "model/x.stl-binary": "stl",
    "model/x.stl-ascii": "stl",
    "application/sla": "stl",
    "model/gltf-binary": "glb",
    "model/gltf+json": "gltf",
}
"""Media types accepted in place of a file name or extension."""

_log = logging.getLogger(__name__)
_INTERNAL_MESSAGE: Final = re.compile(
    r"array|shape|dtype|sequence|index \d+ is out of bounds|object|NoneType|attribute|"
    r"unpack|not subscriptable|argument", re.I)
"""Words of numpy and Python internals that a parse failure's message must not show."""

_OBJ_REF_TAIL: Final = re.compile(r"/\S*")
"""The ``/vt/vn`` tail of an OBJ face entry."""


def resolve_format(filename_or_type: str, supported: tuple[str, ...] = LOAD_FORMATS) -> str:
    """Normalise a file name, extension (``"obj"``, ``".OBJ"``) or media type to a format name.

    Args:
        filename_or_type: A file name, a bare extension or a media type.
        supported: The format names to accept.

    Returns:
        The lower-case format name, one of ``supported``.

    Raises:
        UnsupportedFormatError: If the result is not in ``supported``.

    Example:
        >>> resolve_format("Bunny.OBJ"), resolve_format("model/gltf-binary")
        ('obj', 'glb')
    """
    s = str(filename_or_type).strip().lower()
    fmt = _ALIASES.get(s)
    if fmt is None:
        fmt = s.rsplit(".", 1)[-1] if "." in s else s
    if fmt not in supported:
        raise UnsupportedFormatError(
            f"unsupported mesh format {fmt or filename_or_type!r}; "
            f"supported: {', '.join(supported)}",
            details={"supported": list(supported)})
    return fmt


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LoadedMesh:
    """A mesh file read as triangles, with what the reading did to its polygons.

    Attributes:
        vertices: (n, 3) float64, every vertex record of the file in order.
        faces: (m, 3) int64 triangles (polygons fan-triangulated, in file order).
        face_polygon: (m,) int64 the file face (0-based record) each triangle comes from.
        polygons: number of file faces with more than three corners.
    """

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    face_polygon: NDArray[np.int64]
    polygons: int

    def report(self) -> dict[str, int]:
        """The ``input`` report's entries of the file: ``file_faces``,
        ``triangulated_polygons`` and ``triangles``."""
        file_faces = int(self.face_polygon.max()) + 1 if len(self.face_polygon) else 0
        return {"file_faces": file_faces, "triangulated_polygons": self.polygons,
                "triangles": len(self.faces)}


def load_mesh(data: bytes, filename_or_type: str) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Read a triangle mesh from file bytes, keeping the file's vertex order and count.

    Args:
        data: The whole file.
        filename_or_type: File name (its extension decides), bare extension (``"off"``,
            ``".ply"``) or media type (``"model/gltf-binary"``); one of :data:`LOAD_FORMATS`.

    Returns:
        ``(vertices, faces)``: (n, 3) float64, finite, C-contiguous, and (m, 3) int64 with
        m >= 1 and indices in ``[0, n)`` (polygons fan-triangulated, see :func:`read_mesh`).

    Raises:
        UnsupportedFormatError: Unknown format.
        MeshFileError: The data cannot be parsed, has no faces, non-finite coordinates or
            out-of-range indices.

    Example:
        >>> vertices, faces = load_mesh(b"v 0 0 0\\nv 1 0 0\\nv 0 1 0\\nf 1 2 3\\n", "obj")
        >>> vertices.shape, faces.tolist()
        ((3, 3), [[0, 1, 2]])
    """
    loaded = read_mesh(data, filename_or_type)
    return loaded.vertices, loaded.faces


def read_mesh(data: bytes, filename_or_type: str) -> LoadedMesh:
    """:func:`load_mesh` with what the reading did: which file face each triangle comes from.

    Args:
        data: The whole file.
        filename_or_type: as for :func:`load_mesh`.

    Returns:
        :class:`LoadedMesh`.

    Raises:
        UnsupportedFormatError, MeshFileError: as :func:`load_mesh`.

    Example:
        A quad and a triangle in an OFF file: the quad becomes two triangles.

        >>> off = b"OFF\\n5 2 0\\n0 0 0\\n1 0 0\\n1 1 0\\n0 1 0\\n2 0 0\\n4 0 1 2 3\\n3 1 4 2\\n"
        >>> loaded = read_mesh(off, "off")
        >>> loaded.faces.tolist(), loaded.face_polygon.tolist(), loaded.polygons
        ([[0, 1, 2], [0, 2, 3], [1, 4, 2]], [0, 0, 1], 1)
    """
    fmt = resolve_format(filename_or_type)
    if isinstance(data, memoryview | bytearray):
        data = bytes(data)
    if not isinstance(data, bytes):
        raise TypeError(f"data must be bytes, got {type(data).__name__}")
    if not data.strip():
        raise MeshFileError("empty file", file_type=fmt)
    face_polygon = None
    try:
        if fmt == "obj":
            vertices, faces, face_polygon = _parse_obj(data)
        elif fmt == "off":
            vertices, faces, face_polygon = _parse_off(_text_as_utf8(data, fmt))
        else:
            vertices, faces, face_polygon = _load_trimesh(_text_as_utf8(data, fmt), fmt)
    except MeshFileError as exc:
        if fmt == "off" and (problem := off_problem(data)):  # the record at fault, in words
            raise MeshFileError(f"cannot parse OFF data: {problem}", file_type=fmt) from exc
        exc.located(file_type=fmt)
        raise
    except (ImportError, MemoryError):  # the environment, not the file: not a client error
        raise
    except Exception as exc:  # trimesh raises all kinds of errors on bad data
        _log.debug("mesh parse failure", exc_info=True)
        raise MeshFileError(f"cannot parse {fmt.upper()} data: {_in_words(exc, data, fmt)}",
                            file_type=fmt) from exc
    if fmt == "off" and (problem := _off_short(data, vertices, faces)):
        raise MeshFileError(problem, file_type=fmt)
    if fmt == "stl":
        vertices, faces = _merge_identical(vertices, faces)
    vertices, faces = _finish(vertices, faces, fmt)
    if face_polygon is None or len(face_polygon) != len(faces):
        face_polygon = np.arange(len(faces), dtype=np.int64)
    face_polygon = np.asarray(face_polygon, dtype=np.int64)
    polygons = int(np.count_nonzero(np.bincount(face_polygon) > 1)) if len(faces) else 0
    return LoadedMesh(vertices, faces, face_polygon, polygons)


def _in_words(exc: Exception, data: bytes, fmt: str) -> str:
    """Why a parser failed, for people: the OFF record at fault
    (:func:`solver.file_diagnosis.off_problem`), else the parser's message unless it is a
    numpy or Python internal (ragged arrays, dtypes), else a plain sentence."""
    if fmt == "off" and (problem := off_problem(data)):
        return problem
    text = str(exc)
    if text and not _INTERNAL_MESSAGE.search(text) and len(text) < 200:
        return text
    return "the file's records do not form a mesh (a truncated or malformed line?)"


def _off_short(data: bytes, vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """The OFF record at fault when the parser read fewer vertices or faces than the file's
    header announces (trimesh drops a truncated last face silently); None otherwise."""
    header = re.match(rb"\s*\w*OFF\s+(\d+)\s+(\d+)", data)
    if header is None:
        return None
    if len(vertices) >= int(header[1]) and len(faces) >= int(header[2]):
        return None
    return off_problem(data)


def load_mesh_file(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """:func:`load_mesh` on a file on disk; the format comes from the file extension.

    Args:
        path: The file.

    Returns:
        ``(vertices, faces)`` as :func:`load_mesh` returns them.
    """
    p = Path(path)
    return load_mesh(p.read_bytes(), p.name)


def _finish(vertices: np.ndarray, faces: np.ndarray, fmt: str
            ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Final dtype/shape/range checks shared by every format."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise MeshFileError(f"no vertices (got array of shape {v.shape})", file_type=fmt)
    if f.size == 0:
        raise MeshFileError("no faces: not a triangle mesh", file_type=fmt)
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshFileError(f"faces are not triangles (shape {f.shape})", file_type=fmt)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeshFileError(f"vertex {i} has a non-finite coordinate", file_type=fmt, index=i)
    bad = ((f < 0) | (f >= v.shape[0])).any(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeshFileError(f"face {i} has a vertex index outside [0, {v.shape[0]})",
                            file_type=fmt, index=i)
    return v, f


def _text_as_utf8(data: bytes, fmt: str) -> bytes:
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


def _parse_obj(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions from every ``v`` line, triangles from the ``v`` index of every ``f`` entry.

    Args:
        data: The OBJ file.

    Returns:
        (n, 3) float64 vertices in ``v``-line order, (m, 3) int64 faces (0-based; each
        k-gon fan-triangulated, :func:`fan_triangulate`) and (m,) int64 the ``f`` record
        of each triangle.
    """
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
    except ValueError as exc:
        raise MeshFileError(f"bad vertex coordinate ({exc})") from exc

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
    except ValueError as exc:
        raise MeshFileError(f"bad face index ({exc})") from exc
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
        lineno = int(np.repeat(f_rows, counts)[np.argmax(bad)]) + 1
        raise MeshFileError(f"line {lineno}: face references a vertex not defined before it",
                            details={"line": lineno})
    triangles, face_polygon = fan_triangulate(counts)
    return vertices, idx[triangles], face_polygon


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


def _load_trimesh(data: bytes, fmt: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """PLY/STL/GLB/glTF through trimesh without any processing or reordering; a PLY's
    polygon faces are triangulated here (:func:`_ply_polygons`)."""
    import trimesh  # deferred: heavy import, and only needed for these formats

    loaded = trimesh.load(io.BytesIO(data), file_type=fmt, process=False,
                          maintain_order=True)
    if isinstance(loaded, trimesh.Scene):
        return (*_single_scene_mesh(loaded, fmt), None)
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshFileError(f"no triangle faces (file holds a {type(loaded).__name__})",
                            file_type=fmt)
    if fmt == "ply":
        polygons = _ply_polygons(loaded.metadata)
        if polygons is not None:
            return (np.asarray(loaded.vertices), *polygons)
    return np.asarray(loaded.vertices), np.asarray(loaded.faces), None


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


def _parse_off(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An OFF file (``OFF``, ``COFF``, ``NOFF``, ``CNOFF``... text header).

    Vertex records keep their first three numbers (colours and normals are ignored); a face
    record ``k i0 ... ik-1 [colour]`` is fan-triangulated (:func:`fan_triangulate`).

    Args:
        data: The OFF file, UTF-8.

    Returns:
        (n, 3) float64 vertices, (m, 3) int64 triangles and (m,) int64 the face record of
        each triangle.
    """
    text = data.decode("utf-8", errors="replace")
    lines = [ln.split("#", 1)[0].split() for ln in text.replace("\r", "\n").split("\n")]
    lines = [ln for ln in lines if ln]
    if not lines or not re.match(r"^[A-Za-z]*OFF", lines[0][0]):
        raise MeshFileError("not an OFF file: the first line must be OFF")
    glued = re.match(r"^([A-Za-z]*OFF)(\S+)$", lines[0][0])  # "OFF8 6 12": counts glued on
    header = [glued.group(1), glued.group(2), *lines[0][1:]] if glued else lines[0]
    if any(word.upper() == "BINARY" for word in header[1:]):
        raise MeshFileError("binary OFF is not supported; save the mesh as text OFF")
    rest = lines[1:]
    counts_line = header[1:] if len(header) >= 3 else (rest.pop(0) if rest else [])
    try:
        n_vertices, n_faces = int(counts_line[0]), int(counts_line[1])
    except (IndexError, ValueError):
        raise MeshFileError("the OFF header needs the vertex and face counts") from None
    if len(rest) < n_vertices + n_faces:
        raise MeshFileError(f"the header announces {n_vertices} vertices and {n_faces} faces "
                            f"but the file has {len(rest)} records")
    try:
        vertices = np.array([ln[:3] for ln in rest[:n_vertices]], dtype=np.float64)
    except ValueError as exc:
        raise MeshFileError(f"bad vertex coordinate ({exc})") from exc
    if vertices.ndim != 2 or (n_vertices and vertices.shape[1] != 3):
        raise MeshFileError("a vertex record needs 3 coordinates")
    records = rest[n_vertices:n_vertices + n_faces]
    try:
        corners = np.array([int(ln[0]) for ln in records], dtype=np.int64)
        short = [k for k, ln in enumerate(records) if len(ln) < corners[k] + 1]
        if short:
            raise MeshFileError(f"face {short[0]} lists fewer indices than its count",
                                index=short[0])
        tokens = np.array([i for ln, k in zip(records, corners, strict=True)
                           for i in ln[1:k + 1]], dtype=np.int64)
    except ValueError as exc:
        raise MeshFileError(f"bad face record ({exc})") from exc
    if len(corners) and corners.min() < 3:
        k = int(np.argmax(corners < 3))
        raise MeshFileError(f"face {k} has fewer than 3 vertices", index=k)
    triangles, polygon = fan_triangulate(corners)
    return vertices.reshape(-1, 3), tokens[triangles].reshape(-1, 3), polygon


def _single_scene_mesh(scene: Any, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    """The triangle meshes of a scene (glTF, multi-solid STL), each instance with its node
    transform applied, concatenated in the scene graph's node order (each primitive's
    vertices in its own order). The parts keep their places: the forms carry each
    component's placement (:mod:`solver.placement`)."""
    import trimesh

    meshes = {name: g for name, g in scene.geometry.items() if isinstance(g, trimesh.Trimesh)}
    if not meshes:
        raise MeshFileError("no triangle mesh found in the data", file_type=fmt)
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
            homog = np.hstack([part, np.ones((part.shape[0], 1))]) @ transform.T
            part = homog[:, :3] / homog[:, 3:4]
        vertices.append(part)
        faces.append(np.asarray(mesh.faces, dtype=np.int64) + offset)
        offset += len(part)
    return np.concatenate(vertices), np.concatenate(faces)


def _merge_identical(vertices: np.ndarray, faces: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical positions; new vertices numbered by first occurrence.

    Args:
        vertices: (k, 3) float positions.
        faces: (m, 3) int indices into ``vertices``.

    Returns:
        (n, 3) float64 unique positions and (m, 3) int64 faces into them.
    """
    v = np.asarray(vertices, dtype=np.float64) + 0.0  # + 0.0 turns -0.0 into 0.0
    if v.shape[0] == 0:
        return v.reshape(0, 3), np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(first, kind="stable")  # unique rows in order of first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    new_index = rank[inverse]  # old vertex -> merged vertex
    return v[first[order]], new_index[np.asarray(faces, dtype=np.int64)]


# --------------------------------------------------------------------------------------------
# Saving
# --------------------------------------------------------------------------------------------

def save_mesh(vertices: ArrayLike, faces: ArrayLike, file_type: str) -> bytes:
    """Write a triangle mesh as file bytes.

    Args:
        vertices: (n, 3) float, finite.
        faces: (m, 3) int, indices in ``[0, n)``.
        file_type: One of :data:`SAVE_FORMATS` (or a file name / media type naming one).

    Returns:
        OBJ/OFF: ASCII with ``%.17g`` coordinates (exact float64 round trip). PLY: binary
        little-endian, ``double`` coordinates, ``int`` indices. STL: binary, float32, three
        unshared corners per face (unreferenced vertices are lost). GLB: float32 positions,
        via trimesh. Every vertex, referenced or not, is written in order (except STL).

    Raises:
        UnsupportedFormatError: Unknown format.
        ShapeMismatchError: The arrays are not (n, 3) and (m, 3).
        NonFiniteValueError: A coordinate is NaN or infinite.
        IndexOutOfRangeError: A face names a vertex outside ``[0, n)``.

    Example:
        >>> import numpy as np
        >>> data = save_mesh(np.eye(3), [[0, 1, 2]], "obj")
        >>> vertices, faces = load_mesh(data, "obj")
        >>> bool((vertices == np.eye(3)).all()), faces.tolist()
        (True, [[0, 1, 2]])
    """
    fmt = resolve_format(file_type, SAVE_FORMATS)
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ShapeMismatchError(f"expected shape (n, 3), got {v.shape}", field="vertices")
    f = np.asarray(faces)
    if f.size == 0:
        f = f.reshape(0, 3)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ShapeMismatchError(f"expected shape (m, 3), got {f.shape}", field="faces")
    f = f.astype(np.int64)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise NonFiniteValueError("non-finite coordinate", field="vertices",
                                  index=int(np.flatnonzero(bad)[0]))
    bad = ((f < 0) | (f >= v.shape[0])).any(axis=1)
    if bad.any():
        raise IndexOutOfRangeError(f"vertex index outside [0, {v.shape[0]})", field="faces",
                                   index=int(np.flatnonzero(bad)[0]))
    if fmt == "obj":
        return _write_obj(v, f)
    if fmt == "off":
        return _write_off(v, f)
    if fmt == "ply":
        return _write_ply(v, f)
    import trimesh

    exported = trimesh.Trimesh(vertices=v, faces=f, process=False).export(file_type=fmt)
    return exported.encode("utf-8") if isinstance(exported, str) else bytes(exported)


def _rows(array: np.ndarray, fmt: str, prefix: str = "") -> str:
    """Format the rows of a 2-D array as text lines (vectorized via ``np.savetxt``)."""
    if array.shape[0] == 0:
        return ""
    buf = io.StringIO()
    np.savetxt(buf, array, fmt=fmt, delimiter=" ", header="", comments="")
    text = buf.getvalue()
    if prefix:
        text = prefix + text[:-1].replace("\n", "\n" + prefix) + "\n"
    return text


def _write_obj(v: np.ndarray, f: np.ndarray) -> bytes:
    return ("# written by fundamental-forms-service\n"
            + _rows(v, "%.17g", "v ") + _rows(f + 1, "%d", "f ")).encode("ascii")


def _write_off(v: np.ndarray, f: np.ndarray) -> bytes:
    head = f"OFF\n{v.shape[0]} {f.shape[0]} 0\n"
    tri = np.hstack([np.full((f.shape[0], 1), 3, dtype=np.int64), f])
    return (head + _rows(v, "%.17g") + _rows(tri, "%d")).encode("ascii")


def _write_ply(v: np.ndarray, f: np.ndarray) -> bytes:
    header = ("ply\nformat binary_little_endian 1.0\ncomment fundamental-forms-service\n"
              f"element vertex {v.shape[0]}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {f.shape[0]}\nproperty list uchar int vertex_indices\n"
              "end_header\n").encode("ascii")
    face_dtype = np.dtype([("n", "u1"), ("idx", "<i4", (3,))])
    rec = np.empty(f.shape[0], dtype=face_dtype)
    rec["n"] = 3
    rec["idx"] = f
    return header + v.astype("<f8").tobytes() + rec.tobytes()
