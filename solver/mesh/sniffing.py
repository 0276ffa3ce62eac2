"""What a mesh file's first bytes say: a file that cannot be the format its name (or media
type) gives, told from its first :data:`SNIFF_BYTES` and its size alone. The service checks
an upload so when it arrives (400 ``unreadable-file``, naming the file and what its start
holds) instead of queueing a job that fails in its worker.

One rule per format, the ``sniff`` of each :class:`solver.mesh.formats.MeshFormat` (a test
fails when a format has none), so the check costs the same for any file size. Each refuses
only what the format's reader refuses too (the reader's words where it has them); what the
first bytes cannot decide (a text file whose start is all comments) is left to the reader.
Text is read as the readers read it: a UTF-16 or UTF-8 byte-order mark says the encoding
(:func:`solver.mesh.mesh_readers.without_bom`), and binary OFF is OFF.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Final

from .mesh_readers import without_bom
from .off_binary import is_binary_off

SNIFF_BYTES: Final = 4096
"""How much of a file the check reads: its first 4 KiB."""
STL_HEADER_BYTES: Final = 84
"""A binary STL's 80-byte header and its uint32 triangle count."""
STL_TRIANGLE_BYTES: Final = 50
"""A binary STL triangle: normal, three corners (12 float32) and a uint16."""
_OBJ_VERTEX: Final = re.compile(rb"(?:^|[\r\n])[ \t]*v[ \t]")
"""An OBJ ``v`` line (what the OBJ reader counts as a vertex)."""
_OFF_KEYWORD: Final = re.compile(rb"[A-Za-z]*OFF")
"""The OFF reader's keyword (``OFF``, ``COFF``, ``NOFF``, ...), leading the first record."""

Sniff = Callable[[bytes, int], "str | None"]
"""A format's rule: (the file's first bytes, its size) -> why it is not that format, or
None (it may be; its reader decides)."""


def _text(head: bytes) -> bytes:
    """The first bytes as the readers take text (:func:`without_bom`) without leading
    whitespace."""
    return without_bom(head).lstrip()


def _whole_lines(head: bytes, whole: bool) -> list[bytes]:
    """The lines of ``head`` that end within it (all of them when it is the ``whole`` file)."""
    lines = head.splitlines()
    if not whole and lines and not head.endswith((b"\n", b"\r")):
        lines.pop()  # cut by the window: its end is unknown
    return lines


def _binary(head: bytes) -> str | None:
    """Why a text format's start is not text: NUL bytes (binary data: an image, an archive,
    a binary mesh)."""
    return "it holds binary data (NUL bytes), not text" if b"\0" in head else None


def _obj(head: bytes, size: int) -> str | None:
    whole, head = size <= len(head), without_bom(head)
    if problem := _binary(head):
        return problem
    if whole and not _OBJ_VERTEX.search(head):
        return "no vertices ('v' lines) found"
    return None


def _off(head: bytes, size: int) -> str | None:
    if is_binary_off(head):
        return None  # its words are binary: solver.mesh.off_binary reads them
    whole, head = size <= len(head), without_bom(head)
    if problem := _binary(head):
        return problem
    for line in _whole_lines(head, whole):
        tokens = line.split(b"#", 1)[0].split()
        if not tokens:
            continue  # a comment or a blank line
        if not _OFF_KEYWORD.match(tokens[0]):
            return "the file does not start with the OFF keyword"
        return None
    return "the file does not start with the OFF keyword" if whole else None


def _ply(head: bytes, size: int) -> str | None:
    first = head.partition(b"\n")[0]  # a header's first line is short: the window holds it
    return None if b"ply" in first.lower() else "the file does not start with the 'ply' line"


def _stl(head: bytes, size: int) -> str | None:
    if _text(head)[:5].lower() == b"solid":
        return None  # ASCII (blank lines and a byte-order mark before 'solid' are skipped)
    if size >= STL_HEADER_BYTES:
        count = int.from_bytes(head[80:84], "little")
        need = STL_HEADER_BYTES + STL_TRIANGLE_BYTES * count
        if size == need:
            return None  # binary: exactly its triangles
        where = f"its count of {count} triangles needs {need} bytes, the file has {size}"
    else:
        where = f"the file has {size} bytes, fewer than the {STL_HEADER_BYTES} of its header"
    return (f"neither an ASCII STL (which starts with 'solid') nor a binary one ({where})")


def _glb(head: bytes, size: int) -> str | None:
    if head[:4] != b"glTF":
        return "a GLB file starts with 'glTF'"
    total = int.from_bytes(head[8:12], "little") if len(head) >= 12 else 0
    if size < total:
        return (f"the file ends after {size} of the {total} bytes its GLB header announces "
                "(truncated?)")
    return None


def _gltf(head: bytes, size: int) -> str | None:
    if _text(head)[:1] == b"{" or (not _text(head) and size > len(head)):
        return None
    return "a glTF file is a JSON object (it starts with '{')"


SNIFFS: Final[dict[str, Sniff]] = {"obj": _obj, "off": _off, "ply": _ply, "stl": _stl,
                                   "glb": _glb, "gltf": _gltf}
"""The rule of each format, by its name: each :class:`~solver.mesh.formats.MeshFormat`'s
``sniff`` (the registry takes them from here)."""

_STARTS: Final[dict[str, Callable[[bytes], bool]]] = {
    "glb": lambda head: head[:4] == b"glTF",
    "ply": lambda head: _text(head)[:3].lower() == b"ply",
    "off": lambda head: bool(re.match(rb"[A-Za-z]*OFF\b", _text(head))),
    "stl": lambda head: _text(head)[:5].lower() == b"solid",
}
"""Formats whose start is unmistakable: what a file of another name looks like."""


def sniff(fmt: str, head: bytes, size: int) -> str | None:
    """Why a file cannot be a ``fmt`` file, from its first bytes and size, or None.

    Args:
        fmt: Its format (a key of :data:`solver.mesh.formats.FORMATS`), whose ``sniff``
            rule decides.
        head: Its first :data:`SNIFF_BYTES` (or all of it).
        size: Its size in bytes.

    Returns:
        The reason in words, with what its start looks like where another format's start
        is unmistakable (``it starts like a GLB file``), or None.

    Example:
        >>> sniff("off", b"\\x89PNG\\r\\n\\x1a\\n\\x00\\x00\\x00\\rIHDR", 2000)
        'it holds binary data (NUL bytes), not text'
        >>> sniff("obj", b"glTF\\x02\\x00\\x00\\x00", 8)
        'it holds binary data (NUL bytes), not text; it starts like a GLB file'
        >>> sniff("off", b"# a comment\\nOFF\\n3 1 0\\n", 20) is None
        True
    """
    from .formats import FORMATS  # the registry imports this module's rules

    known = FORMATS.get(fmt)
    problem = known.sniff(head, size) if known is not None and known.sniff else None
    if problem is None:
        return None
    like = next((name for name, starts in _STARTS.items() if name != fmt and starts(head)),
                None)
    return problem + (f"; it starts like a {like.upper()} file" if like else "")


def leading_bytes(head: bytes, count: int = 16) -> str:
    """A file's first ``count`` bytes as a problem quotes them (escaped like a Python bytes
    literal, without the ``b''``).

    Example:
        >>> leading_bytes(b"\\x89PNG\\r\\n\\x1a\\n\\x00")
        '\\\\x89PNG\\\\r\\\\n\\\\x1a\\\\n\\\\x00'
    """
    return repr(bytes(head[:count]))[2:-1]
