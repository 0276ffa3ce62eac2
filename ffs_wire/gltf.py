"""A ``.gltf`` file as it is sent: its buffers that are separate files beside it embedded as
``data:`` URIs, separate images dropped (a mesh needs no texture), so that a service, which
gets bytes alone, can read it.

The rule is the library's :func:`solver.mesh.gltf_documents.embed_buffers`, which reads a
``.gltf`` from disk (``ffs``, :func:`solver.mesh.io.load_mesh_file`); the client must not
import the library and the library must not import this package
(``tests/test_package_boundaries.py``), so the rule is written twice, and
``tests/client/test_client_gltf.py`` checks that both give the same bytes. Standard library
only.

Example:
    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> _ = (folder / "box.bin").write_bytes(b"\\x00\\x01")
    >>> sent = embed_buffers(b'{"buffers": [{"uri": "box.bin", "byteLength": 2}]}', folder)
    >>> json.loads(sent)["buffers"][0]["uri"]
    'data:application/octet-stream;base64,AAE='
"""

from __future__ import annotations

import base64
import codecs
import json
import os
from pathlib import Path
from typing import Any
from urllib.parse import unquote

DATA_URI = "data:"


class BufferFileError(ValueError):
    """A buffer of a ``.gltf`` names a file beside it that cannot be read.

    Attributes:
        index: the buffer (``buffers[index]``).
        uri: its URI as the document writes it.
        reason: why, in words (``cannot read its file 'box.bin' beside the document (No
            such file or directory)``).
    """

    def __init__(self, index: int, uri: str, reason: str) -> None:
        self.index, self.uri, self.reason = index, uri, reason
        super().__init__(f"buffer {index}: {reason}")


def without_bom(data: bytes) -> bytes:
    """Text as UTF-8 without a byte-order mark: UTF-16 (by its mark) decoded, UTF-8's mark
    dropped, text without a mark as it is (the library's
    :func:`solver.mesh.mesh_readers.without_bom`)."""
    if data.startswith((codecs.BOM_UTF16_BE, codecs.BOM_UTF16_LE)):
        return data.decode("utf-16", errors="replace").encode("utf-8")
    if data.startswith(codecs.BOM_UTF8):
        return data[len(codecs.BOM_UTF8):]
    return data


def _document(data: bytes) -> dict[str, Any] | None:
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def embed_buffers(data: bytes, folder: Path) -> bytes:
    """A ``.gltf`` document with every separate buffer read from ``folder`` and embedded as
    a ``data:`` URI, and separate images dropped; other data as it is.

    Args:
        data: The ``.gltf`` file (UTF-8).
        folder: Its folder (relative URIs resolve there).

    Returns:
        The document's bytes (the same bytes when nothing is separate, or when they are not
        a JSON object: the service then says what they are).

    Raises:
        BufferFileError: a buffer's file that cannot be read, naming the buffer and its URI.
    """
    doc = _document(data)
    if doc is None:
        return data
    buffers = doc.get("buffers")
    separate = ([(k, str(b["uri"])) for k, b in enumerate(buffers)
                 if isinstance(b, dict) and isinstance(b.get("uri"), str)
                 and not b["uri"].startswith(DATA_URI)] if isinstance(buffers, list) else [])
    images = [image for image in doc.get("images") or []
              if isinstance(image, dict) and isinstance(image.get("uri"), str)
              and not image["uri"].startswith(DATA_URI)]
    if not separate and not images:
        return data
    for index, uri in separate:
        try:
            payload = (folder / unquote(uri)).read_bytes()
        except OSError as exc:
            raise BufferFileError(index, uri, f"cannot read its file {uri!r} beside the "
                                  f"document ({exc.strerror or exc})") from None
        doc["buffers"][index]["uri"] = ("data:application/octet-stream;base64,"
                                        + base64.b64encode(payload).decode("ascii"))
    for image in images:
        del image["uri"]  # textures are not read: an image file is not needed
    return json.dumps(doc).encode("utf-8")


def file_bytes(path: str | os.PathLike[str]) -> bytes:
    """A mesh file's bytes as they are sent: a ``.gltf`` (by its extension) without a
    byte-order mark and with its separate buffers embedded (:func:`embed_buffers`); any
    other file as it is.

    Raises:
        OSError: the file cannot be read. BufferFileError: a buffer file it names cannot.
    """
    path = Path(path)
    data = path.read_bytes()
    if path.suffix.lower() == ".gltf":
        return embed_buffers(without_bom(data), path.parent)
    return data


__all__ = ["BufferFileError", "embed_buffers", "file_bytes", "without_bom"]
