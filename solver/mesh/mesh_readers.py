"""The mesh file parsers behind :mod:`solver.mesh.formats`' readers: OFF parsed here (OBJ in
:mod:`solver.mesh.obj_reader`), PLY, STL, GLB and glTF through trimesh (no processing, the
file's vertex order kept), and what they share (text decoding, fan triangulation of polygons,
numeric blocks, STL's merge of identical corners). The rules per format are
:mod:`solver.mesh.io`'s docstring; every parser returns ``(vertices, faces, face_polygon)``:
(n, 3) float, (m, 3) int triangles and the file face of each triangle (None: one file face
per triangle).
"""

from __future__ import annotations

import io
import re
import warnings
from typing import Any, Final

import numpy as np

from ..core.errors import MeshFileError
from .file_diagnosis import off_problem
from .strips import strip_triangles


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
    record ``k i0 ... ik-1 [colour]`` is fan-triangulated (:func:`fan_triangulate`). A file
    whose records are one per line and whose faces all have the same width is read in two
    numpy blocks (:func:`_off_blocks`, ~5x faster at a million faces); any other file, and
    every malformed one, record by record (the errors name the record at fault).

    Args:
        data: The OFF file, UTF-8.

    Returns:
        (n, 3) float64 vertices, (m, 3) int64 triangles and (m,) int64 the face record of
        each triangle.
    """
    blocks = _off_blocks(data)
    if blocks is not None:
        return blocks
    text = data.decode("utf-8", errors="replace")
    lines = [ln.split("#", 1)[0].split() for ln in text.replace("\r", "\n").split("\n")]
    lines = [ln for ln in lines if ln]
    n_vertices, n_faces, used = _off_header(lines[:2])
    rest = lines[used:]
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
        raise MeshFileError("binary OFF is not supported; save the mesh as text OFF")
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
    vertices = number_block(data[start:vertex_end], np.float64, n_vertices)
    faces = number_block(data[vertex_end + 1:face_end], np.int64, n_faces)
    if vertices is None or faces is None or vertices.shape[1] < 3:
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


def merge_identical(vertices: np.ndarray, faces: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical positions; new vertices numbered by first occurrence.

    The positions are sorted by a hash of their bits (one stable argsort: ~5x faster than
    ``np.unique(axis=0)`` at a million faces); when two different positions share a hash
    they are sorted by their coordinates instead (:func:`_sorted_positions`).

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
    order, same = _sorted_positions(v)
    starts = np.concatenate([[True], ~same])
    group = np.cumsum(starts) - 1  # the group of each position, in sorted order
    first = order[starts]  # stable sorts: a group's first member is its first occurrence
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    new_index = np.empty(len(v), dtype=np.int64)
    new_index[order] = rank[group]  # old vertex -> merged vertex
    return v[np.sort(first)], new_index[np.asarray(faces, dtype=np.int64)]


_MIX: Final = (np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB), np.uint64(31))
"""SplitMix64's finalizer constants: two odd multipliers and a shift."""


def _sorted_positions(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A stable order of (k, 3) float64 positions that puts identical ones next to each other.

    Returns:
        ``(order, same)``: (k,) int64 the order, and (k - 1,) bool whether each sorted
        position equals the one before it.
    """
    bits = v.view(np.uint64)
    first, second, shift = _MIX
    key = bits[:, 0].copy()
    for column in (1, 2):
        key *= first
        key ^= key >> shift
        key ^= bits[:, column]
    key *= second
    key ^= key >> shift
    order = np.argsort(key, kind="stable")
    ordered = v[order]
    same = (ordered[1:] == ordered[:-1]).all(axis=1)
    sorted_key = key[order]
    if (same != (sorted_key[1:] == sorted_key[:-1])).any():  # a hash two positions share
        order = np.lexsort(v.T[::-1])
        ordered = v[order]
        same = (ordered[1:] == ordered[:-1]).all(axis=1)
    return order, same
