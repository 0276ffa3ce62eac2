"""Why a text OFF file does not read as a mesh, in words: the record at fault, its line, and
what the header announced (instead of the numpy message a parser raises on ragged rows).

:func:`off_problem` walks an ASCII OFF file's records the way the format defines them
(``OFF`` or ``COFF``/``NOFF``/... keyword, ``n_vertices n_faces n_edges``, ``n_vertices``
lines of at least three coordinates, ``n_faces`` lines ``k i_1 ... i_k``; ``#`` comments and
blank lines skipped) and names the first record that breaks it. :func:`solver.mesh.io.load_mesh`
calls it when its parser failed or read fewer records than the header announces, so it costs
nothing on a good file.

Example:
    >>> off_problem(b"OFF\\n3 1 0\\n0 0 0\\n1 0 0\\n0 1\\n3 0 1 2\\n")
    'line 5: vertex 2 has 2 coordinates, expected 3'
    >>> off_problem(b"OFF\\n3 1 0\\n0 0 0\\n1 0 0\\n0 1 0\\n")
    'the file ends after 0 of the 1 faces its header announces (truncated?)'
"""

from __future__ import annotations

from collections.abc import Iterator

KEYWORD_SUFFIX = "OFF"
"""OFF's header keyword ends so (``OFF``, ``COFF``, ``NOFF``, ``STOFF``, ...)."""


def _records(text: str) -> Iterator[tuple[int, list[str]]]:
    """``(line number, tokens)`` of each line with data (comments and blanks skipped)."""
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split("#", 1)[0].split()
        if tokens:
            yield number, tokens


def _numbers(tokens: list[str], kind: type) -> list | None:
    try:
        return [kind(t) for t in tokens]
    except ValueError:
        return None


def off_problem(data: bytes) -> str | None:
    """The first thing that keeps ASCII OFF ``data`` from being a mesh, in words (None when
    its records are complete and well formed, or when it is binary OFF).

    Args:
        data: The whole file.

    Returns:
        ``"line 5: vertex 2 has 2 coordinates, expected 3"``, ``"the file ends after 3 of
        the 4 vertices its header announces (truncated?)"``, ... or None.
    """
    text = data.decode("utf-8", "replace")
    records = _records(text)
    number, tokens = next(records, (0, []))
    if not tokens or not tokens[0].upper().endswith(KEYWORD_SUFFIX):
        return "the file does not start with the OFF keyword"
    if len(tokens) > 1 and tokens[1].upper() == "BINARY":
        return None
    counts_tokens = tokens[1:] or next(records, (number, []))[1]
    counts = _numbers(counts_tokens[:3], int)
    if counts is None or len(counts) < 2:
        return (f"line {number + 1}: the header needs the vertex and face counts "
                f"('n_vertices n_faces n_edges'), found {' '.join(counts_tokens) or 'nothing'}")
    n_vertices, n_faces = counts[0], counts[1]
    for index in range(n_vertices):
        number, tokens = next(records, (0, []))
        if not tokens:
            return (f"the file ends after {index} of the {n_vertices} vertices its header "
                    "announces (truncated?)")
        if _numbers(tokens[:3], float) is None:
            return (f"line {number}: vertex {index} has a coordinate that is not a number: "
                    f"'{' '.join(tokens[:3])}'")
        if len(tokens) < 3:
            return f"line {number}: vertex {index} has {len(tokens)} coordinates, expected 3"
    for index in range(n_faces):
        number, tokens = next(records, (0, []))
        if not tokens:
            return (f"the file ends after {index} of the {n_faces} faces its header "
                    "announces (truncated?)")
        values = _numbers(tokens, int)
        if values is None:
            return f"line {number}: face {index} is not a list of integers: '{' '.join(tokens)}'"
        if values[0] < 3 or len(values) - 1 < values[0]:
            return (f"line {number}: face {index} lists {len(values) - 1} vertex indices, "
                    f"its count says {values[0]}")
    return None


# ------------------------------------------------------------- binary files cut short

_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2,
              "int16": 2, "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4,
              "float": 4, "float32": 4, "double": 8, "float64": 8}
"""Bytes of each PLY scalar type."""
STL_HEADER_BYTES = 84
"""A binary STL's 80-byte header and its uint32 triangle count."""
STL_TRIANGLE_BYTES = 50
"""A binary STL triangle: normal and three corners (12 float32) and a uint16."""


def _ends_early(kept: int, total: int, what: str, have: int, need: int) -> str:
    return (f"the file ends after {kept} of the {total} {what} its header announces "
            f"({have} of at least {need} bytes; truncated?)")


def stl_problem(data: bytes) -> str | None:
    """Why a binary STL file is short of the triangles its header counts, or an ASCII one
    ends without ``endsolid``, in words (None for a complete file).

    Example:
        >>> import struct
        >>> stl_problem(bytes(80) + struct.pack("<I", 4) + bytes(120))[:57]
        'the file ends after 2 of the 4 triangles its header annou'
    """
    if data[:5].lower() == b"solid" and b"facet" in data[:1024].lower():  # ASCII
        if b"endsolid" in data[-1024:].lower():
            return None
        facets = data.lower().count(b"endfacet")
        return (f"the file ends after {facets} complete facets, without the 'endsolid' line "
                "of an ASCII STL (truncated?)")
    if len(data) < STL_HEADER_BYTES:
        return (f"the file ends inside the binary STL header ({len(data)} of "
                f"{STL_HEADER_BYTES} bytes; truncated?)")
    count = int.from_bytes(data[80:84], "little")
    need = STL_HEADER_BYTES + STL_TRIANGLE_BYTES * count
    if len(data) >= need:
        return None
    kept = (len(data) - STL_HEADER_BYTES) // STL_TRIANGLE_BYTES
    return _ends_early(kept, count, "triangles", len(data), need)


def glb_problem(data: bytes) -> str | None:
    """Why a GLB file is shorter than its header says, in words (None when it is complete
    or not a GLB).

    Example:
        >>> import struct
        >>> glb_problem(b"glTF" + struct.pack("<II", 2, 400) + bytes(100))
        'the file ends after 112 of the 400 bytes its GLB header announces (truncated?)'
    """
    if data[:4] != b"glTF" or len(data) < 12:
        return None
    total = int.from_bytes(data[8:12], "little")
    if len(data) >= total:
        return None
    return (f"the file ends after {len(data)} of the {total} bytes its GLB header "
            "announces (truncated?)")


def _ply_header(data: bytes) -> tuple[str, list[tuple[str, int, list[list[str]]]], int] | None:
    """A PLY header's format, its elements ``(name, count, properties)`` and the data's
    offset; None without a complete header."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        return None
    newline = data.find(b"\n", end)
    offset = len(data) if newline < 0 else newline + 1
    fmt, elements = "", []
    for line in data[:end].decode("ascii", "replace").splitlines():
        tokens = line.split()
        if tokens[:1] == ["format"] and len(tokens) > 1:
            fmt = tokens[1]
        elif tokens[:1] == ["element"] and len(tokens) > 2 and tokens[2].isdigit():
            elements.append((tokens[1], int(tokens[2]), []))
        elif tokens[:1] == ["property"] and elements:
            elements[-1][2].append(tokens[1:])
    return fmt, elements, offset


def _ply_min_bytes(element: str, properties: list[list[str]]) -> int | None:
    """The fewest bytes one binary record of these properties takes (a list: its count, and
    three entries for a face's vertex indices, a triangle), or None for a type this does not
    know."""
    size = 0
    for prop in properties:
        if prop[:1] == ["list"] and len(prop) > 3:
            count, item = _PLY_SIZES.get(prop[1]), _PLY_SIZES.get(prop[2])
            if count is None or item is None:
                return None
            corners = element == "face" and prop[3] in ("vertex_indices", "vertex_index")
            size += count + 3 * item * corners
        elif prop and prop[0] in _PLY_SIZES:
            size += _PLY_SIZES[prop[0]]
        else:
            return None
    return size


def ply_problem(data: bytes) -> str | None:
    """Why a PLY file holds fewer records than its header announces, in words (None when it
    holds at least that much, or its header cannot be read).

    A binary file is measured against the fewest bytes its elements need (lists as
    triangles); an ASCII file's data lines are counted.

    Example:
        >>> head = b"ply\\nformat ascii 1.0\\nelement vertex 3\\nproperty float x\\n"
        >>> ply_problem(head + b"end_header\\n0\\n1\\n")
        'the file ends after 2 of the 3 data lines its header announces (truncated?)'
    """
    header = _ply_header(data)
    if header is None:
        return None
    fmt, elements, offset = header
    total = sum(count for _, count, _ in elements)
    if fmt == "ascii":
        last = data[max(data.rfind(b"\n") + 1, offset):]  # a last line without newline
        lines = data.count(b"\n", offset) + bool(last.strip())  # no copy of the body
        if lines >= total:  # one record per line: fewer lines, fewer records
            return None
        return (f"the file ends after {lines} of the {total} data lines its header announces "
                "(truncated?)")
    need = 0
    for name, count, properties in elements:
        size = _ply_min_bytes(name, properties)
        if size is None:
            return None
        need += count * size
    have = len(data) - offset
    if have >= need:
        return None
    named = " and ".join(f"{count} {name}" for name, count, _ in elements)
    return (f"the file ends after {have} bytes of data, short of the {need} bytes its "
            f"header's {named} records need at least (truncated?)")
