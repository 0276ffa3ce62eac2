"""The one registry of mesh file formats: for each format its names (extension, media
types), its reader and writer, whether it keeps polygons, the precision it stores and what
else it can carry (an atlas, morph-target animation, several parts).

:mod:`solver.mesh.io` reads and writes through it (:func:`~solver.mesh.io.load_mesh`,
:func:`~solver.mesh.io.save_mesh`), the service takes its uploads' types from it and ``ffs`` its
file formats; glTF is written by the one writer :mod:`solver.mesh.gltf`.

Example:
    >>> FORMATS["ply"].precision, FORMATS["stl"].precision, FORMATS["gltf"].writes
    ('float64', 'float32', True)
    >>> [f.name for f in FORMATS.values() if "texcoords" in f.carries]
    ['obj', 'glb', 'gltf']
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np

from ..core.errors import MeshFileError, UnsupportedFormatError
from . import gltf
from .file_diagnosis import glb_problem, off_problem, ply_problem, stl_problem
from .gltf_documents import draco_problem, glb_document, gltf_problem, triangle_lists
from .mesh_readers import (
    ascii_stl_text,
    load_trimesh,
    merge_identical,
    off_short,
    parse_off,
    text_as_utf8,
    without_bom,
)
from .obj_reader import parse_obj
from .off_binary import is_binary_off, parse_binary_off
from .sniffing import SNIFFS

Parsed = tuple[np.ndarray, np.ndarray, np.ndarray | None]
"""A reader's answer: vertices (n, 3), triangles (m, 3), the file face of each triangle."""
Reader = Callable[[bytes], Parsed]
Writer = Callable[[np.ndarray, np.ndarray], bytes]
"""A writer: checked (n, 3) float64 vertices, (m, 3) int64 faces -> the file's bytes."""


@dataclass(frozen=True)
class MeshFormat:
    """One mesh file format.

    Attributes:
        name: its name and file extension (lower case).
        read: its reader (bytes -> :data:`Parsed`).
        write: its writer, or None (read only).
        media_types: media types that name it (an upload's ``Content-Type``).
        polygons: its faces may be polygons (read fan-triangulated, in file order).
        precision: the coordinates it stores (``float64``: a save/load round trip is exact).
        carries: what it holds besides one mesh: ``texcoords`` (an atlas), ``animation``
            (morph targets), ``parts`` (several meshes with their transforms).
        diagnose: names the record at fault in a file that does not parse (OFF), or what a
            file cut short lacks (PLY, STL, GLB), or None.
        complete: a cheap check (from the header's counts) run on every file that parsed:
            what a file cut short lacks, or None; a parser may read the records that are
            there and stop (PLY, STL, GLB: the same as ``diagnose``).
        sniff: what the file's first bytes and size rule out, or None
            (:mod:`solver.mesh.sniffing`: an upload is checked with it when it arrives).
        prepare: what the file's bytes become before they are read and checked, or None:
            text formats (OBJ, OFF, glTF's JSON) take a byte-order mark as their encoding
            (:func:`~solver.mesh.mesh_readers.without_bom`: UTF-16 read as UTF-8); an ASCII
            STL also loses what comes before ``solid``
            (:func:`~solver.mesh.mesh_readers.ascii_stl_text`).
    """

    name: str
    read: Reader
    write: Writer | None
    media_types: tuple[str, ...] = ()
    polygons: bool = False
    precision: Literal["float64", "float32"] = "float64"
    carries: tuple[str, ...] = ()
    diagnose: Callable[[bytes], str | None] | None = None
    complete: Callable[[bytes], str | None] | None = None
    prepare: Callable[[bytes], bytes] | None = None
    sniff: Callable[[bytes, int], str | None] | None = None

    @property
    def writes(self) -> bool:
        return self.write is not None


# ----------------------------------------------------------------------------- writers

def text_rows(array: np.ndarray, fmt: str, prefix: str = "") -> str:
    """The rows of a 2-D array as text lines, each led by ``prefix`` (``np.savetxt``)."""
    if array.shape[0] == 0:
        return ""
    buffer = io.StringIO()
    np.savetxt(buffer, array, fmt=fmt, delimiter=" ", header="", comments="")
    text = buffer.getvalue()
    return prefix + text[:-1].replace("\n", "\n" + prefix) + "\n" if prefix else text


def _write_obj(v: np.ndarray, f: np.ndarray) -> bytes:
    return ("# written by fundamental-forms-service\n"
            + text_rows(v, "%.17g", "v ") + text_rows(f + 1, "%d", "f ")).encode("ascii")


def _write_off(v: np.ndarray, f: np.ndarray) -> bytes:
    head = f"OFF\n{v.shape[0]} {f.shape[0]} 0\n"
    tri = np.hstack([np.full((f.shape[0], 1), 3, dtype=np.int64), f])
    return (head + text_rows(v, "%.17g") + text_rows(tri, "%d")).encode("ascii")


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


def _write_stl(v: np.ndarray, f: np.ndarray) -> bytes:
    import trimesh  # deferred: heavy import, and only needed for STL

    return bytes(trimesh.Trimesh(vertices=v, faces=f, process=False).export(file_type="stl"))


# ----------------------------------------------------------------------------- readers

def _read_off(data: bytes) -> Parsed:
    """OFF (text, or binary: :mod:`solver.mesh.off_binary`), and a text file shorter than its
    header announces named at its first bad record."""
    if is_binary_off(data):
        return parse_binary_off(data)
    vertices, faces, face_polygon = parse_off(text_as_utf8(data, "off"))
    if problem := off_short(data, vertices, faces):
        raise MeshFileError(problem, file_type="off")
    return vertices, faces, face_polygon


def _read_stl(data: bytes) -> Parsed:
    """STL, with bit-identical corners merged into shared vertices."""
    vertices, faces, _ = load_trimesh(text_as_utf8(data, "stl"), "stl")
    return (*merge_identical(vertices, faces), None)


def _trimesh_reader(fmt: str) -> Reader:
    return lambda data: load_trimesh(text_as_utf8(data, fmt), fmt)


def _read_glb(data: bytes) -> Parsed:
    """GLB through trimesh, unless its meshes are Draco-compressed and cannot be decoded;
    triangle strips and fans as triangle lists
    (:func:`~solver.mesh.gltf_documents.triangle_lists`)."""
    if problem := draco_problem(glb_document(data)):
        raise MeshFileError(problem, file_type="glb")
    return load_trimesh(triangle_lists(data, "glb"), "glb")


def _read_gltf(data: bytes) -> Parsed:
    """A ``.gltf`` document through trimesh, unless a buffer is a separate file or its
    meshes cannot be decoded (:mod:`solver.mesh.gltf_documents`); triangle strips and fans
    as triangle lists (:func:`~solver.mesh.gltf_documents.triangle_lists`)."""
    if problem := gltf_problem(data):
        raise MeshFileError(problem, file_type="gltf")
    return load_trimesh(triangle_lists(data, "gltf"), "gltf")


FORMATS: Final[dict[str, MeshFormat]] = {f.name: f for f in (
    MeshFormat("obj", parse_obj, _write_obj, ("model/obj",), polygons=True,
               carries=("texcoords",), prepare=without_bom, sniff=SNIFFS["obj"]),
    MeshFormat("off", _read_off, _write_off, polygons=True, diagnose=off_problem,
               prepare=without_bom,
               sniff=SNIFFS["off"]),
    MeshFormat("ply", _trimesh_reader("ply"), _write_ply, polygons=True,
               diagnose=ply_problem,
               complete=ply_problem, sniff=SNIFFS["ply"]),
    MeshFormat("stl", _read_stl, _write_stl,
               ("model/stl", "model/x.stl-binary", "model/x.stl-ascii", "application/sla"),
               precision="float32", diagnose=stl_problem,
               complete=stl_problem, prepare=ascii_stl_text, sniff=SNIFFS["stl"]),
    MeshFormat("glb", _read_glb,
               lambda v, f: gltf.encode_gltf(v, f, kind="glb"), ("model/gltf-binary",),
               precision="float32", carries=("texcoords", "animation", "parts"),
               diagnose=glb_problem,
               complete=glb_problem, sniff=SNIFFS["glb"]),
    MeshFormat("gltf", _read_gltf,
               lambda v, f: gltf.encode_gltf(v, f, kind="gltf"), ("model/gltf+json",),
               precision="float32", carries=("texcoords", "animation", "parts"),
               prepare=without_bom,
               sniff=SNIFFS["gltf"]),
)}
"""Every mesh file format, by name (``.gltf`` as bytes: buffers as ``data:`` URIs only; from
disk, :func:`solver.mesh.io.load_mesh_file` embeds the files beside it)."""

LOAD_FORMATS: Final = tuple(FORMATS)
"""Formats :func:`solver.mesh.io.load_mesh` reads (lower-case names / file extensions)."""
SAVE_FORMATS: Final = tuple(name for name, f in FORMATS.items() if f.writes)
"""Formats :func:`solver.mesh.io.save_mesh` writes."""
_MEDIA_TYPES: Final = {media: f.name for f in FORMATS.values() for media in f.media_types}


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
    fmt = _MEDIA_TYPES.get(s)
    if fmt is None:
        fmt = s.rsplit(".", 1)[-1] if "." in s else s
    if fmt not in supported:
        raise UnsupportedFormatError(
            f"unsupported mesh format {fmt or filename_or_type!r}; "
            f"supported: {', '.join(supported)}",
            details={"supported": list(supported)})
    return fmt


__all__ = ["FORMATS", "LOAD_FORMATS", "SAVE_FORMATS", "MeshFormat", "resolve_format",
           "text_rows"]
