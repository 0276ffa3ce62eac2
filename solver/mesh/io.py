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
  face colours are ignored). A record may run over several lines (a face's indices one a
  line, as libigl reads them); it then ends with its last line, and only a record on one
  line carries further columns (the rule: :mod:`solver.mesh.mesh_readers`). Binary OFF
  (``OFF BINARY``: Geomview's big-endian words or pmp-library's little-endian ones, with or
  without face colours) is read by :mod:`solver.mesh.off_binary`.
* **PLY** -- trimesh (``process=False``); polygon faces are read back from the file's face
  list and triangulated here; a ``tristrips`` element (triangle strips, ``-1`` restarts) is
  unrolled into its triangles (:mod:`solver.mesh.strips`).
* **Polygons** -- in OBJ, OFF and PLY a face with k > 3 corners ``(v0, ..., vk-1)`` is
  fan-triangulated into the k - 2 triangles ``(v0, vj, vj+1)``, j = 1 .. k - 2, in file order
  (the same rule in every format; :func:`read_mesh` reports how many faces were polygons and
  which file face each triangle comes from). Answers are given on these triangles.
* **STL** -- trimesh, then merge of bit-identical positions (``-0.0`` equals ``0.0``).
* **GLB** / **glTF** (``.gltf`` as bytes only with ``data:`` URI buffers; from disk,
  :func:`load_mesh_file` embeds the buffer files beside it; Draco-compressed meshes are
  refused: :mod:`solver.mesh.gltf_documents`) -- trimesh. Every triangle
  mesh primitive of every node instance is taken with its node transform applied (skipped
  when it is the identity, so positions are bit-exact), concatenated in the scene graph's node
  order: the parts of a multi-part model are components of one mesh, and the forms keep each
  component's placement (:mod:`solver.mesh.placement`). A multi-solid ASCII STL is read the same
  way (then merged). Triangle strips and fans are read as triangle lists (a strip's every
  second triangle flipped, its repeated-index triangles dropped, as PLY's; a fan's as a
  polygon's: :func:`solver.mesh.gltf_documents.triangle_lists`). Points and lines are
  ignored.

Saving (:func:`save_mesh`): OBJ, OFF and PLY with full float64 precision (``%.17g`` text,
binary little-endian ``double`` PLY) so a save/load round trip is exact; STL (float32,
unshared vertices) through trimesh; GLB and ``.gltf`` (float32, embedded buffer) by the one
glTF writer :mod:`solver.mesh.gltf`.

Formats, their readers and writers and what each carries are one registry,
:data:`solver.mesh.formats.FORMATS`; the parsers are :mod:`solver.mesh.mesh_readers` and
:mod:`solver.mesh.obj_reader`.

All parse failures raise :class:`~solver.core.errors.MeshFileError` (a
:class:`~solver.core.errors.SolverInputError`) with a ``reason``; unknown formats raise its subclass
:class:`~solver.core.errors.UnsupportedFormatError`. The HTTP service answers them 400
``unreadable-file`` and 415 ``unsupported-file-type``.
"""

from __future__ import annotations

import importlib
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import (
    IndexOutOfRangeError,
    MeshFileError,
    NonFiniteValueError,
    ShapeMismatchError,
    UnsupportedFormatError,
)
from .formats import FORMATS, LOAD_FORMATS, SAVE_FORMATS, resolve_format
from .gltf_documents import embed_buffers
from .mesh_readers import fan_triangulate, without_bom

__all__ = [
    "LOAD_FORMATS",
    "SAVE_FORMATS",
    "LoadedMesh",
    "MeshFileError",
    "UnsupportedFormatError",
    "fan_triangulate",
    "import_readers",
    "load_mesh",
    "load_mesh_file",
    "read_mesh",
    "resolve_format",
    "save_mesh",
]

_log = logging.getLogger(__name__)
_INTERNAL_MESSAGE: Final = re.compile(
    r"array|shape|dtype|sequence|index \d+ is out of bounds|object|NoneType|attribute|"
    r"unpack|not subscriptable|argument", re.I)
"""Words of numpy and Python internals that a parse failure's message must not show."""

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


READER_MODULES: tuple[str, ...] = ("trimesh",)
"""The modules the readers import only when first needed (trimesh: PLY, STL, GLB and glTF;
~0.4 s): :func:`import_readers` imports them, and a service's process pool preloads them."""


def import_readers() -> None:
    """Import what the readers defer (:data:`READER_MODULES`) now.

    A long-lived process that reads files, such as a service worker, calls this once at
    start, so the first file it reads does not pay the import within that request's time.

    Example:
        >>> import sys
        >>> import_readers()
        >>> "trimesh" in sys.modules
        True
    """
    for module in READER_MODULES:
        importlib.import_module(module)


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
    reader = FORMATS[fmt]
    if reader.prepare is not None:
        data = reader.prepare(data)
    try:
        vertices, faces, face_polygon = reader.read(data)
    except MeshFileError as exc:  # a reader's own words carry its file type
        # the record at fault where the reader had no words; a cut file in any case
        check = reader.diagnose if exc.file_type is None else reader.complete
        if check and (problem := check(data)):
            raise MeshFileError(f"cannot parse {fmt.upper()} data: {problem}",
                                file_type=fmt) from exc
        exc.located(file_type=fmt)
        raise
    except (ImportError, MemoryError):  # the environment, not the file: not a client error
        raise
    except Exception as exc:  # trimesh raises all kinds of errors on bad data
        _log.debug("mesh parse failure", exc_info=True)
        raise MeshFileError(f"cannot parse {fmt.upper()} data: {_in_words(exc, data, fmt)}",
                            file_type=fmt) from exc
    if reader.complete and (problem := reader.complete(data)):  # read what was there
        raise MeshFileError(f"cannot parse {fmt.upper()} data: {problem}", file_type=fmt)
    vertices, faces = _finish(vertices, faces, fmt)
    if face_polygon is None or len(face_polygon) != len(faces):
        face_polygon = np.arange(len(faces), dtype=np.int64)
    face_polygon = np.asarray(face_polygon, dtype=np.int64)
    polygons = int(np.count_nonzero(np.bincount(face_polygon) > 1)) if len(faces) else 0
    return LoadedMesh(vertices, faces, face_polygon, polygons)


def _in_words(exc: Exception, data: bytes, fmt: str) -> str:
    """Why a parser failed, for people: the OFF record at fault
    (:func:`solver.mesh.file_diagnosis.off_problem`), else the parser's message unless it is a
    numpy or Python internal (ragged arrays, dtypes), else a plain sentence."""
    diagnose = FORMATS[fmt].diagnose
    if diagnose and (problem := diagnose(data)):
        return problem
    text = str(exc)
    if text and not _INTERNAL_MESSAGE.search(text) and len(text) < 200:
        return text
    if fmt in ("gltf", "glb"):
        return ("its accessors, buffer views and nodes do not fit together (a malformed "
                "document?)")
    return "the file's records do not form a mesh (a truncated or malformed line?)"


def load_mesh_file(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """:func:`load_mesh` on a file on disk; the format comes from the file extension.

    Args:
        path: The file.

    Returns:
        ``(vertices, faces)`` as :func:`load_mesh` returns them.
    """
    p = Path(path)
    return load_mesh(file_bytes(p), p.name)


def file_bytes(path: Path, fmt: str | None = None) -> bytes:
    """A mesh file's bytes as :func:`load_mesh` takes them: a ``.gltf`` document with the
    buffer files beside it embedded (:func:`solver.mesh.gltf_documents.embed_buffers`).

    Args:
        path: The file.
        fmt: Its format when not its extension's.

    Raises:
        OSError: the file cannot be read. MeshFileError: a buffer file it names cannot.
    """
    data = path.read_bytes()
    if resolve_format(fmt or path.name) == "gltf":
        return embed_buffers(without_bom(data), path.parent)
    return data


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
        unshared corners per face (unreferenced vertices are lost). GLB / glTF: float32
        positions and normals (:func:`solver.mesh.gltf.encode_gltf`). Every vertex, referenced
        or not, is written in order (except STL).

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
    write = FORMATS[fmt].write
    assert write is not None  # resolve_format checked it is one of SAVE_FORMATS
    return write(v, f)
