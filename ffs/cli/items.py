"""The items of a command line: which inputs make one unit of work, where it is written
(``-o`` as a file, a template or a folder), and the row that records what it did."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

DEFAULT_EXTENSIONS = {"forms": ".json", "check": ".json", "reconstruct": ".obj",
                      "vjp": ".npz"}
"""Output extension when ``-o`` is a folder (others: the input's, if writable, else .obj)."""


OUTPUT_FORMATS = {"forms": ("json", "npz"), "check": ("json",), "vjp": ("json", "npz")}
"""Command -> the formats its outputs may have (the others: :func:`mesh_outputs`)."""


def mesh_outputs() -> tuple[str, ...]:
    """What a mesh result is written as (``--format`` or the extension): the formats the
    library writes (:data:`solver.mesh.formats.SAVE_FORMATS`), ``json`` and ``npz``. Imports the
    library: call it after the BLAS thread variables are set."""
    from solver.mesh.formats import SAVE_FORMATS

    return (*SAVE_FORMATS, "json", "npz")


class UsageError(Exception):
    """A command line that cannot run (exit 2)."""


def output_format(command: str, path: str, override: str | None = None) -> str:
    """The format ``path`` is written in by ``command``: ``override`` (``--format``) or its
    extension.

    Raises:
        UsageError: A format the command cannot write (checked before any work).
    """
    fmt = (override or Path(path).suffix.lstrip(".")).lower()
    writable = OUTPUT_FORMATS.get(command) or mesh_outputs()
    if fmt not in writable:
        raise UsageError(f"cannot write {path} as {fmt or '(no extension)'!r}: {command} "
                         f"writes {', '.join(writable)} (the extension, or --format)")
    return fmt


def check_output_formats(command: str, items: Sequence[Item], override: str | None) -> None:
    """Every output of ``items`` has a format ``command`` writes (:func:`output_format`),
    so a bad ``-o`` is a usage error before any computation."""
    for item in items:
        for out in item.outputs:
            output_format(command, out, override)


SHAPE_COMMANDS: tuple[str, ...] = ("blend", "mean")
"""The commands whose inputs are one blend's shapes (``POST /v1/blend``, ``solver.blend``)."""


def check_shape_count(command: str, inputs: Sequence[str]) -> None:
    """``ffs blend`` and ``ffs mean`` take as many meshes as the library's blend: 1 to
    :data:`solver.shape_space.MAX_SHAPES` (the one home of the limit, which the service's
    ``/v1/blend`` reads too). Imports the library: call it after the BLAS thread variables
    are set.

    Raises:
        UsageError: More meshes than that (checked before any work).
    """
    from solver.shape_space import MAX_SHAPES

    if command in SHAPE_COMMANDS and not 1 <= len(inputs) <= MAX_SHAPES:
        raise UsageError(f"{command} takes 1 to {MAX_SHAPES} meshes with the same faces; "
                         f"got {len(inputs)}")


def check_server(server: str | None) -> None:
    """``--server`` (or ``FFS_SERVER``) is an http(s) URL with a host, so that a bare
    ``127.0.0.1:8000`` is a usage error before any work, not a failure of every input.

    Raises:
        UsageError: Another scheme, or no host.

    Example:
        >>> check_server("http://127.0.0.1:8000")
        >>> check_server("127.0.0.1:8000")
        Traceback (most recent call last):
        ...
        ffs.cli.items.UsageError: --server (or FFS_SERVER) '127.0.0.1:8000' is not a URL: \
give http:// or https:// and the host, e.g. http://127.0.0.1:8000
    """
    if server is None:
        return
    parts = urlsplit(server)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        example = f"http://{parts.netloc}{parts.path}" if "//" in server else f"http://{server}"
        raise UsageError(f"--server (or FFS_SERVER) {server!r} is not a URL: give http:// or "
                         f"https:// and the host, e.g. {example}")


def _handles_up_front(path: str) -> Any:
    """A JSON handles file, read once for every input (a ``.sel`` / ``.def`` pair selects on
    each input's mesh: None, read per input)."""
    from ffs import files
    from ffs.selections import is_selection_file

    return None if is_selection_file(path) else files.read_handles(path)


def _json_up_front(path: str) -> Any:
    """A JSON document (``--constraints``), read once for every input."""
    from ffs import files

    return files.read_json(path)


def _mesh_up_front(path: str) -> Any:
    """A reference mesh (``--align-to``): its (n, 3) vertices, read once for every input."""
    from ffs import files

    return files.read_mesh(path)[0]


def _cotangent_up_front(path: str) -> Any:
    """A cotangent (``--cotangent``): its (n, 3) or (k, n, 3) array, read once for every
    input."""
    from ffs import files

    return files.read_cotangent(path)


GIVEN_FILES: dict[str, Callable[[str], Any] | None] = {
    "align_to": _mesh_up_front, "handles": _handles_up_front,
    "cotangent": _cotangent_up_front, "constraints": _json_up_front}
"""The options that name one file every item reads (``--align-to``, ``--handles``,
``--cotangent``, ``--constraints``): checked before any work by :func:`check_given_files`,
each with the reader that reads it once for the command where what it holds does not depend
on the item (None: read by each item; a ``.sel`` / ``.def`` handle set, which selects on each
input's mesh, is read per item by its reader answering None). A local worker process gets
what they hold once, when it starts (:mod:`ffs.cli.batch`)."""


def check_given_files(args: Any) -> None:
    """Every file an option names (:data:`GIVEN_FILES`) exists, and a ``.sel`` / ``.def``
    handle set has its other half beside it; a file with a reader is read now, once, into
    ``args.given`` (option -> what it holds; the runners take it from there). So a mistyped
    name or a file that is not what its option takes (handles that are not JSON, an
    ``--align-to`` that is not a mesh, a ``--cotangent`` that is not (n, 3) numbers) is a
    usage error (exit 2) before any computation, not a failure of each input file.

    Raises:
        UsageError: ``--handles moves.json: moves.json: cannot read it as JSON: ...``.
    """
    from ffs.files import InputFileError
    from ffs.selections import is_selection_file, selection_pair

    args.given = {}
    for name, read in GIVEN_FILES.items():
        path = getattr(args, name, None)
        if path is None:
            continue
        flag = "--" + name.replace("_", "-")
        paths = [Path(path)]
        if name == "handles" and is_selection_file(path):
            paths += [half for half in selection_pair(path) if half != paths[0]]
        for file in paths:
            if not file.is_file():
                beside = f" (the other half of {paths[0].name})" if file != paths[0] else ""
                raise UsageError(f"{flag} {path}: no such file {file}{beside}")
        if read is not None:
            try:
                args.given[name] = read(path)
            except InputFileError as exc:
                raise UsageError(f"{flag} {exc}") from None


@dataclass
class Item:
    """One unit of work.

    Attributes:
        index: Position among the command line's items (the ``{index}`` template field).
        inputs: Its input files: one, or two (A and B) for a blend.
        outputs: Its output paths: one, one per ``-t`` value of a blend, none for a
            ``check`` without ``-o``.
    """

    index: int
    inputs: list[str]
    outputs: list[str]

    @property
    def name(self) -> str:
        """The input files' names, joined with `` + ``."""
        return " + ".join(Path(p).name for p in self.inputs)


@dataclass
class Row:
    """What one item did: the summary table's row and the report's entry.

    Attributes:
        file: The item's name.
        outputs: The item's output paths.
        status: ``ok``, ``failed``, ``stopped`` (interrupted while running) or ``skipped``
            (not run: ``--fail-fast``).
        path: The input paths, joined with `` + `` (prefix of the error line).
        faces: Faces of the result, when there is one.
        seconds: Wall time of the run.
        refined: Whether the refinement ran (None: the operation has none).
        length_error: Max edge-length error after refinement (``flatten``: the layout's
            mean edge-length change, the statistic of its warning).
        angle_error: Max dihedral-angle error after refinement (``flatten``: the layout's
            mean corner-angle change, largest per face).
        note: The summary table's ``result`` cell.
        outcome: The refinement's outcome in words (``converged after 3 iterations``,
            ``partly: time limit after 2 iterations``, ``not refined: ...``; "" without one).
        warnings: The report's ``warnings``: thresholds the answer is past.
        error: One line naming what failed (field and index where known).
        pid: The process that ran it.
        started: Wall-clock start (``time.time()``).
        finished: Wall-clock end.
        report: The operation's full report.
        extra: More fields of the report's entry (e.g. ``integrable``, ``traceback``).
    """

    file: str
    outputs: list[str]
    status: str = "ok"
    path: str = ""
    faces: int | None = None
    seconds: float = 0.0
    refined: bool | None = None
    length_error: float | None = None
    angle_error: float | None = None
    note: str = ""
    outcome: str = ""
    warnings: list[dict[str, Any]] = field(default_factory=list)
    error: str | None = None
    pid: int = 0
    started: float = 0.0
    finished: float = 0.0
    report: Any = None
    extra: dict[str, Any] = field(default_factory=dict)


def skipped_row(item: Item) -> Row:
    """The row of an item that ``--fail-fast`` kept from running."""
    return Row(item.name, item.outputs, status="skipped", error="not run (--fail-fast)")


SEQUENCE_FILES = (".glb", ".json", ".npz")
"""Outputs that hold every row of a blend in one file: an animated GLB (morph targets),
or the rows as arrays."""


def _template_fields(path: Path, index: int) -> dict[str, Any]:
    return {"stem": path.stem, "name": path.name, "parent": str(path.parent),
            "index": index, "ext": path.suffix.lstrip(".")}


def _default_extension(command: str, first_input: str) -> str:
    if command in DEFAULT_EXTENSIONS:
        return DEFAULT_EXTENSIONS[command]
    suffix = Path(first_input).suffix.lower()
    return suffix if suffix in (".obj", ".off", ".ply", ".stl", ".glb") else ".obj"


def plan_items(command: str, inputs: Sequence[str], output: str | None,
               t_values: Sequence[float] | None = None,
               output_format: str | None = None) -> list[Item]:
    """The items of a command line: inputs grouped and outputs named.

    Args:
        command: The subcommand (``blend`` takes its two inputs as one item).
        inputs: The input paths, in command-line order.
        output: ``-o``: a file, a template (``{stem}``, ``{name}``, ``{parent}``,
            ``{index}``, ``{ext}``, ``{t}``) or a folder; None only for ``check``.
        t_values: A blend's ``-t`` values (several need ``{t}`` or ``{index}``).
        output_format: ``--format``: in a folder, the outputs get its extension (not the
            command's default one, which would put, say, glTF in a ``.obj`` file).

    Returns:
        One :class:`Item` per input (per pair for a blend), in input order.

    Raises:
        UsageError: ``-o`` missing, not a template for several inputs, a bad template, or
            two items that would write the same file.

    Example:
        >>> [item.outputs for item in plan_items("convert", ["a.off", "b.off"], "{stem}.ply")]
        [['a.ply'], ['b.ply']]
    """
    together = command in ("blend", "mean", "transfer")  # one item of all the inputs
    groups = [list(inputs)] if together else [[p] for p in inputs]
    if output is None:
        if command != "check":
            raise UsageError(f"{command} needs -o OUTPUT (a file, a template with {{stem}}, "
                             "or a folder)")
        return [Item(i, g, []) for i, g in enumerate(groups)]
    templated = "{" in output
    folder = output.endswith(("/", os.sep)) or Path(output).is_dir()
    many_t = t_values is not None and len(t_values) > 1
    if folder and not templated:
        extension = (f".{output_format.lower()}" if output_format
                     else _default_extension(command, groups[0][0]))
        output = str(Path(output) / ("{stem}" + ("-{t}" if many_t else "") + extension))
    elif not templated and len(groups) > 1:
        raise UsageError(f"{len(groups)} inputs cannot all be written to {output}: use a "
                         "template such as -o 'out/{stem}.glb' or a folder")
    elif not templated and many_t and Path(output).suffix.lower() in SEQUENCE_FILES:
        return [Item(0, groups[0], [output])]  # every row in one file (animation, arrays)
    elif not templated and many_t:
        raise UsageError("several -t values (or rows of --weights) need a template with {t} "
                         "or {index} in -o, or one .glb (an animation), .json or .npz file")
    items, seen = [], {}
    for i, group in enumerate(groups):
        fields = _template_fields(Path(group[0]), i)
        try:
            if many_t:
                outs = [output.format(**{**fields, "index": k}, t=f"{t:g}")
                        for k, t in enumerate(t_values or [])]
            else:
                t0 = f"{t_values[0]:g}" if t_values else ""
                outs = [output.format(**fields, t=t0)]
        except (KeyError, IndexError, ValueError) as exc:
            raise UsageError(f"bad output template {output!r}: {exc}; fields: stem, name, "
                             "parent, index, ext, t") from None
        for out in outs:
            if out in seen:
                raise UsageError(f"{group[0]} and {seen[out]} would both be written to {out}")
            seen[out] = group[0]
        items.append(Item(i, group, outs))
    return items
