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

Triangle strips (``mode`` 5) and triangle fans (``mode`` 6) are rewritten as triangle lists
(``mode`` 4) before trimesh reads the document (:func:`triangle_lists`; trimesh skips fans,
and reads strips keeping their joins): a strip ``s0 s1 s2 s3 ...`` holds ``(s0, s1, s2)``,
``(s2, s1, s3)``, ``(s2, s3, s4)``, ... (every second triangle flipped, as PLY's
``tristrips``: :func:`solver.mesh.strips.strip_triangles`) with the triangles that repeat an
index dropped (the joins of strips stitched into one); a fan ``f0 f1 f2 ...`` holds
``(f0, f1, f2)``, ``(f0, f2, f3)``, ... (as a polygon is fan-triangulated). Each triangle is
a rotation of the glTF 2.0 specification's (section 3.7.2.1), so the winding is the file's.
"""

from __future__ import annotations

import base64
import importlib.util
import json
import struct
from pathlib import Path
from typing import Any
from urllib.parse import unquote, unquote_to_bytes

import numpy as np

from ..core.errors import MeshFileError
from .strips import strip_triangles

DATA_URI = "data:"
DRACO = "KHR_draco_mesh_compression"
GLB_MAGIC = b"glTF"
TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN = 4, 5, 6
"""glTF primitive modes (glTF 2.0 specification, section 5.24.5: ``mesh.primitive.mode``)."""
_MODE_NAMES = {TRIANGLE_STRIP: "triangle strip", TRIANGLE_FAN: "triangle fan"}
_INDEX_TYPES = {5121: np.dtype("<u1"), 5123: np.dtype("<u2"), 5125: np.dtype("<u4")}
"""An index accessor's component types: unsigned byte, short and int."""
_UNSIGNED_INT, _ELEMENT_ARRAY_BUFFER = 5125, 34963
_CHUNK_JSON, _CHUNK_BIN = b"JSON", b"BIN\x00"


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
            "ffs.Client, solver.mesh.io.load_mesh_file) takes the files beside it")


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


# --------------------------------------------------------------------- strips and fans

def fan_triangles(indices: np.ndarray) -> np.ndarray:
    """The triangles of a triangle fan ``f0 f1 f2 ...``: ``(f0, f(i+1), f(i+2))``.

    Args:
        indices: (L,) int the fan's vertex indices.

    Returns:
        (max(L - 2, 0), 3) int64 triangles, in order (those repeating an index kept, as a
        polygon's are: the mesh's checks name them).

    Example:
        >>> fan_triangles(np.array([0, 1, 2, 3, 4])).tolist()
        [[0, 1, 2], [0, 2, 3], [0, 3, 4]]
    """
    idx = np.asarray(indices, dtype=np.int64).ravel()
    if len(idx) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    return np.stack([np.full(len(idx) - 2, idx[0]), idx[1:-1], idx[2:]], axis=1)


def _glb_chunks(data: bytes) -> tuple[dict[str, Any], bytes | None] | None:
    """The JSON document and the BIN chunk (None without one) of a GLB file whose chunks
    are all there; None otherwise (its reader says what is wrong)."""
    if len(data) < 20 or data[:4] != GLB_MAGIC:
        return None
    end = min(int.from_bytes(data[8:12], "little"), len(data))
    offset, doc, binary = 12, None, None
    while offset + 8 <= end:
        length, kind = struct.unpack_from("<I4s", data, offset)
        chunk = data[offset + 8:offset + 8 + length]
        if len(chunk) != length:
            return None
        if kind == _CHUNK_JSON and offset == 12:
            doc = _document(chunk)
        elif kind == _CHUNK_BIN and binary is None:
            binary = chunk
        offset += 8 + length
    return None if doc is None else (doc, binary)


class _Buffers:
    """A document's buffers as bytes, each decoded once: ``data:`` URIs, and a GLB's BIN
    chunk as its buffer 0; ``size``: the file's bytes (more than any accessor's count)."""

    def __init__(self, doc: dict[str, Any], binary: bytes | None, kind: str,
                 size: int) -> None:
        self.doc, self.binary, self.kind, self.size = doc, binary, kind, size
        self.decoded: dict[int, bytes] = {}

    def __getitem__(self, k: int) -> bytes:
        if k not in self.decoded:
            self.decoded[k] = self._decode(k)
        return self.decoded[k]

    def _decode(self, k: int) -> bytes:
        buffers = self.doc.get("buffers") or []
        buffer = buffers[k] if isinstance(k, int) and 0 <= k < len(buffers) else None
        if not isinstance(buffer, dict):
            raise MeshFileError(f"buffers[{k}]: the document has no such buffer",
                                file_type=self.kind, index=k)
        uri = buffer.get("uri")
        if uri is None and self.kind == "glb" and k == 0 and self.binary is not None:
            return self.binary
        if not isinstance(uri, str) or not uri.startswith(DATA_URI):
            raise MeshFileError(f"buffers[{k}]: its data is not in the file (uri {uri!r}): "
                                "send the model as GLB, or as .gltf with its buffers "
                                "embedded (data: URIs)", file_type=self.kind, index=k)
        header, _, payload = uri.partition(",")
        try:
            if header.endswith(";base64"):
                return base64.b64decode(payload, validate=False)
            return unquote_to_bytes(payload)
        except ValueError:
            raise MeshFileError(f"buffers[{k}]: its data: URI is not valid base64",
                                file_type=self.kind, index=k) from None


def _index_accessor(doc: dict[str, Any], k: Any, buffers: _Buffers, where: str
                    ) -> np.ndarray:
    """The (count,) int64 indices accessor ``k`` holds (tightly packed or strided)."""
    accessors = doc.get("accessors") or []
    accessor = accessors[k] if isinstance(k, int) and 0 <= k < len(accessors) else None
    if not isinstance(accessor, dict):
        raise MeshFileError(f"{where}: its indices are accessors[{k}], which the document "
                            "does not have", file_type=buffers.kind)
    name = f"accessors[{k}]"
    dtype = _INDEX_TYPES.get(accessor.get("componentType"))  # type: ignore[arg-type]
    if dtype is None or accessor.get("type", "SCALAR") != "SCALAR":
        raise MeshFileError(f"{name}: the indices of {where} are not unsigned integer "
                            f"scalars (componentType {accessor.get('componentType')}, type "
                            f"{accessor.get('type')})", file_type=buffers.kind, index=k)
    if "sparse" in accessor or "bufferView" not in accessor:
        raise MeshFileError(f"{name}: the indices of {where} are sparse or have no buffer "
                            "view, which this reader does not take", file_type=buffers.kind,
                            index=k)
    v = accessor["bufferView"]
    view = doc["bufferViews"][v]
    data = buffers[view["buffer"]]
    count = int(accessor["count"])
    start = int(view.get("byteOffset", 0)) + int(accessor.get("byteOffset", 0))
    stride = int(view.get("byteStride") or dtype.itemsize)
    end = min(int(view.get("byteOffset", 0)) + int(view["byteLength"]), len(data))
    if count < 0 or (count and start + (count - 1) * stride + dtype.itemsize > end):
        raise MeshFileError(f"{name}: its {count} indices run past the end of "
                            f"bufferViews[{v}]", file_type=buffers.kind, index=k)
    return np.ndarray((count,), dtype=dtype, buffer=data, offset=start,
                      strides=(stride,)).astype(np.int64)


def _primitive_indices(doc: dict[str, Any], primitive: dict[str, Any], buffers: _Buffers,
                       where: str) -> np.ndarray:
    """A primitive's vertex indices: its index accessor's, or ``0 .. count - 1`` of its
    ``POSITION`` accessor when it has none (drawn in vertex order)."""
    try:
        if "indices" in primitive:
            return _index_accessor(doc, primitive["indices"], buffers, where)
        position = primitive["attributes"]["POSITION"]
        count = int(doc["accessors"][position]["count"])
        if not 0 <= count <= buffers.size:  # every vertex takes bytes of the file
            raise MeshFileError(f"accessors[{position}]: the {count} positions of {where} are "
                                f"more than the file's {buffers.size} bytes hold",
                                file_type=buffers.kind, index=position)
        return np.arange(count, dtype=np.int64)
    except MeshFileError:
        raise
    except KeyError as exc:
        raise MeshFileError(f"{where}: its indices cannot be found (no {exc.args[0]!r} "
                            "where the document should have one)",
                            file_type=buffers.kind) from None
    except (TypeError, ValueError, IndexError):
        raise MeshFileError(f"{where}: its indices' accessor, buffer view and buffer do not "
                            "fit together", file_type=buffers.kind) from None


def _glb(doc: dict[str, Any], binary: bytes) -> bytes:
    """A GLB file of ``doc`` and its BIN chunk (chunks padded to 4 bytes, as specified)."""
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = [struct.pack("<I4s", len(js), _CHUNK_JSON), js]
    if binary:
        binary += b"\x00" * (-len(binary) % 4)
        chunks += [struct.pack("<I4s", len(binary), _CHUNK_BIN), binary]
    body = b"".join(chunks)
    return GLB_MAGIC + struct.pack("<II", 2, 12 + len(body)) + body


def _add_triangle_lists(doc: dict[str, Any], rewritten: list[tuple[dict[str, Any], np.ndarray]],
                        binary: bytes | None, kind: str) -> bytes | None:
    """Each ``(primitive, triangles (t, 3))`` of ``rewritten`` made a triangle list: its
    triangles a new uint32 accessor and bufferView, in a new ``data:`` URI buffer of a
    ``.gltf`` or at the end of a GLB's BIN chunk (made buffer 0 when there is none).

    Returns:
        The GLB's new BIN chunk (``binary`` as it was for a ``.gltf``).
    """
    blob = b"".join(t.astype("<u4").tobytes() for _, t in rewritten)
    views = doc.setdefault("bufferViews", [])
    accessors = doc.setdefault("accessors", [])
    doc_buffers = doc.setdefault("buffers", [])
    if kind == "glb":  # the new indices go into the BIN chunk: buffer 0
        if binary is None or (doc_buffers and isinstance(doc_buffers[0], dict)
                              and "uri" in doc_buffers[0]):
            for view in views:  # no BIN chunk yet: it becomes buffer 0
                if isinstance(view, dict) and isinstance(view.get("buffer"), int):
                    view["buffer"] += 1
            doc_buffers.insert(0, {"byteLength": 0})
            binary = b""
        target, base = 0, len(binary) + (-len(binary) % 4)
        binary = binary + b"\x00" * (base - len(binary)) + blob
        doc_buffers[0]["byteLength"] = len(binary)
    else:
        target, base = len(doc_buffers), 0
        doc_buffers.append({"byteLength": len(blob),
                            "uri": "data:application/octet-stream;base64,"
                                   + base64.b64encode(blob).decode("ascii")})
    offset = base
    for primitive, triangles in rewritten:
        views.append({"buffer": target, "byteOffset": offset, "byteLength": 4 * triangles.size,
                      "target": _ELEMENT_ARRAY_BUFFER})
        accessors.append({"bufferView": len(views) - 1, "componentType": _UNSIGNED_INT,
                          "count": int(triangles.size), "type": "SCALAR"})
        primitive["indices"], primitive["mode"] = len(accessors) - 1, TRIANGLES
        offset += 4 * triangles.size
    return binary


def triangle_lists(data: bytes, kind: str) -> bytes:
    """A glTF document with every triangle strip and triangle fan primitive rewritten as a
    triangle list (``mode`` 4), for trimesh to read.

    Each strip's or fan's triangles (the module's rules: a strip's every second triangle
    flipped and its repeated-index triangles dropped, a fan's as a polygon's) become a new
    ``uint32`` index accessor in a new bufferView: in a new ``data:`` URI buffer of a
    ``.gltf``, or appended to a GLB's BIN chunk. A strip or fan left with no triangle is
    removed from its mesh. Draco-compressed primitives are left to their decoder.

    Args:
        data: A ``.gltf`` document (buffers as ``data:`` URIs) or a GLB file.
        kind: ``"gltf"`` or ``"glb"``.

    Returns:
        The rewritten document, or ``data`` itself when it has no strip or fan (or does not
        parse: its reader says why).

    Raises:
        MeshFileError: A strip's or fan's indices that cannot be read (naming the primitive
            and its accessor), or strips and fans without a triangle in a document that
            has nothing else to read.

    Example:
        A square drawn as the strip 0 1 2 3 (no index accessor: vertex order):

        >>> doc = {"meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 5}]}],
        ...        "accessors": [{"count": 4, "componentType": 5126, "type": "VEC3"}],
        ...        "buffers": []}
        >>> out = json.loads(triangle_lists(json.dumps(doc).encode(), "gltf"))
        >>> out["meshes"][0]["primitives"][0]["mode"], out["accessors"][1]["count"]
        (4, 6)
        >>> uri = out["buffers"][0]["uri"]
        >>> np.frombuffer(base64.b64decode(uri.split(",")[1]), "<u4").reshape(-1, 3).tolist()
        [[0, 1, 2], [2, 1, 3]]
    """
    binary: bytes | None = None
    if kind == "glb":
        chunks = _glb_chunks(data)
        if chunks is None:
            return data
        doc, binary = chunks
    else:
        parsed = _document(data)
        if parsed is None:
            return data
        doc = parsed
    meshes = [mesh for mesh in doc.get("meshes") or [] if isinstance(mesh, dict)]
    targets = [(m, p, primitive) for m, mesh in enumerate(meshes)
               for p, primitive in enumerate(mesh.get("primitives") or [])
               if isinstance(primitive, dict)
               and primitive.get("mode") in (TRIANGLE_STRIP, TRIANGLE_FAN)
               and DRACO not in (primitive.get("extensions") or {})]
    if not targets:
        return data
    buffers = _Buffers(doc, binary, kind, len(data))
    rewritten, empty = [], []
    for m, p, primitive in targets:
        where = f"meshes[{m}].primitives[{p}]"
        indices = _primitive_indices(doc, primitive, buffers, where)
        if primitive["mode"] == TRIANGLE_STRIP:
            triangles = strip_triangles(indices)[0]
        else:
            triangles = fan_triangles(indices)
        if len(triangles):
            rewritten.append((primitive, triangles))
        else:
            empty.append((where, primitive, len(indices)))
    dropped = [id(primitive) for _, primitive, _ in empty]
    for mesh in meshes:
        mesh["primitives"] = [q for q in mesh.get("primitives") or [] if id(q) not in dropped]
    if not rewritten:
        left = [q for mesh in meshes for q in mesh.get("primitives") or []
                if isinstance(q, dict) and q.get("mode", TRIANGLES) == TRIANGLES]
        if not left:
            where, primitive, count = empty[0]
            raise MeshFileError(f"{where}: its {_MODE_NAMES[primitive['mode']]} of {count} "
                                "indices holds no triangle (each repeats an index)",
                                file_type=kind)
    if rewritten:
        binary = _add_triangle_lists(doc, rewritten, binary, kind)
    if kind == "glb":
        return _glb(doc, binary or b"")
    return json.dumps(doc, separators=(",", ":")).encode("utf-8")
