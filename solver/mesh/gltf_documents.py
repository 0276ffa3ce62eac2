"""What a glTF document needs before trimesh reads it: buffers that are files beside a
``.gltf``, and compression trimesh cannot undo.

A ``.gltf`` file is JSON; its binary data (vertex positions, indices) sits in buffers, each
either inside the document as a ``data:`` URI or in a separate file named by a relative URI
(``"uri": "model.bin"``). Bytes alone (an upload, :func:`solver.mesh.io.read_mesh`) cannot
reach a separate file, so such a document is refused in words that say what to send
(:func:`gltf_problem`); a file on disk (:func:`solver.mesh.io.load_mesh_file`, the command
line) has its buffers read from its folder and embedded first (:func:`embed_buffers`).
Images are never needed for the mesh: a separate image file is dropped from the document.

Draco-compressed primitives (``KHR_draco_mesh_compression``) need the optional DracoPy
decoder; without it trimesh reads their positions as zeros (assimp's
``glTF2/draco/2CylinderEngine.gltf``: 110,336 triangles at the origin), so such a file is
refused in words instead (:func:`draco_problem`).
"""

from __future__ import annotations

import base64
import importlib.util
import json
import struct
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from ..core.errors import MeshFileError

DATA_URI = "data:"
DRACO = "KHR_draco_mesh_compression"
GLB_MAGIC = b"glTF"


def _document(data: bytes) -> dict[str, Any] | None:
    """The glTF JSON document, or None when ``data`` is not a JSON object."""
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def separate_buffers(doc: dict[str, Any]) -> list[tuple[int, str]]:
    """``(index, uri)`` of every buffer whose data is a separate file (a URI that is not a
    ``data:`` URI)."""
    buffers = doc.get("buffers")
    if not isinstance(buffers, list):
        return []
    return [(k, str(b["uri"])) for k, b in enumerate(buffers)
            if isinstance(b, dict) and isinstance(b.get("uri"), str)
            and not b["uri"].startswith(DATA_URI)]


def glb_document(data: bytes) -> dict[str, Any] | None:
    """The JSON chunk of a GLB file, or None when it has none that parses."""
    if len(data) < 20 or data[:4] != GLB_MAGIC:
        return None
    length, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON":
        return None
    return _document(data[20:20 + length])


def draco_problem(doc: dict[str, Any] | None) -> str | None:
    """Why a glTF document cannot be read when it uses Draco compression and its decoder
    (DracoPy) is not installed; None otherwise."""
    if doc is None or importlib.util.find_spec("DracoPy") is not None:
        return None
    used = set(doc.get("extensionsUsed") or []) | set(doc.get("extensionsRequired") or [])
    if DRACO not in used:
        return None
    return (f"the meshes are Draco-compressed ({DRACO}), which this service does not "
            "decode: export the model without Draco compression")


def gltf_problem(data: bytes) -> str | None:
    """Why a ``.gltf`` document given as bytes cannot be read: a buffer that is a separate
    file, or Draco compression (:func:`draco_problem`); None otherwise.

    Example:
        >>> gltf_problem(b'{"buffers": [{"uri": "box.bin", "byteLength": 840}]}')[:39]
        "buffer 0 is the separate file 'box.bin'"
    """
    doc = _document(data)
    if problem := draco_problem(doc):
        return problem
    separate = separate_buffers(doc) if doc is not None else []
    if not separate:
        return None
    index, uri = separate[0]
    return (f"buffer {index} is the separate file {uri!r}: send the model as GLB, or as "
            ".gltf with its buffers embedded (data: URIs); a .gltf read from disk (ffs, "
            "solver.mesh.io.load_mesh_file) takes the files beside it")


def embed_buffers(data: bytes, folder: Path) -> bytes:
    """A ``.gltf`` document with every separate buffer read from ``folder`` and embedded as
    a ``data:`` URI, and separate images dropped; other data as it is.

    Args:
        data: The ``.gltf`` file.
        folder: Its folder (relative URIs resolve there).

    Returns:
        The document's bytes (the same bytes when nothing is separate).

    Raises:
        MeshFileError: a buffer's file that cannot be read, naming its URI.
    """
    doc = _document(data)
    if doc is None:
        return data
    separate = separate_buffers(doc)
    images = [image for image in doc.get("images") or []
              if isinstance(image, dict) and isinstance(image.get("uri"), str)
              and not image["uri"].startswith(DATA_URI)]
    if not separate and not images:
        return data
    for index, uri in separate:
        path = folder / unquote(uri)
        try:
            payload = path.read_bytes()
        except OSError as exc:
            raise MeshFileError(f"buffer {index}: cannot read its file {uri!r} beside the "
                                f"document ({exc.strerror or exc})", file_type="gltf",
                                index=index, details={"value": uri}) from None
        doc["buffers"][index]["uri"] = ("data:application/octet-stream;base64,"
                                        + base64.b64encode(payload).decode("ascii"))
    for image in images:
        del image["uri"]  # textures are not read: an image file is not needed
    return json.dumps(doc).encode("utf-8")
