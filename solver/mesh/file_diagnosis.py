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
