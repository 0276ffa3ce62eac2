"""``ffs``: the command line. ``ffs <command> <inputs...> -o <output> [options]``.

Commands: ``forms`` (edge lengths and dihedral angles), ``check`` (integrability),
``reconstruct`` (a mesh from forms), ``deform`` (handles), ``flatten`` (parameterize),
``blend`` (interpolate two meshes), ``convert`` (read, check, write), ``serve`` (the
service, ``python -m service``).

* In-process through :mod:`solver` by default; ``--server URL`` (or ``FFS_SERVER``) runs the
  same work on a service through :class:`ffs.client.Client` (as jobs: stage progress, no
  request timeout).
* Many inputs at once: ``-o`` is a template (``{stem}``, ``{name}``, ``{parent}``,
  ``{index}``, ``{t}`` for blends) or a folder; ``-j N`` runs N at a time (local worker
  processes with ``cores / N`` BLAS threads each unless ``--threads``, or N concurrent jobs
  on the server); a failing file is reported and the rest carry on (``--fail-fast`` stops).
* A progress bar per running file with its stage (on a terminal; quiet otherwise or with
  ``-q``), then a summary table on stdout; ``--report FILE`` writes every file's full report.
* Exit codes: 0 all done, 1 a file failed (its message names the file, field and index),
  2 usage; 130 interrupted. Bad input never prints a traceback (``-v`` shows the traceback
  of an unexpected error).
"""

from __future__ import annotations

import argparse
import concurrent.futures as futures
import multiprocessing
import os
import queue
import re
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ffs import __version__

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
DEFAULT_EXTENSIONS = {"forms": ".json", "check": ".json", "reconstruct": ".obj"}
"""Output extension when ``-o`` is a folder (others: the input's, if writable, else .obj)."""
MESH_OUTPUTS = ("reconstruct", "deform", "flatten", "blend", "convert")


class UsageError(Exception):
    """A command line that cannot run (exit 2)."""


class StoppedError(Exception):
    """The batch was stopped (Ctrl-C or --fail-fast) while this file ran."""


# ----------------------------------------------------------------------------- items


@dataclass
class Item:
    """One unit of work: its inputs (one file, two for a blend) and output path(s)."""

    index: int
    inputs: list[str]
    outputs: list[str]

    @property
    def name(self) -> str:
        return " + ".join(Path(p).name for p in self.inputs)


@dataclass
class Row:
    """What one item did: the summary table's row and the report's entry."""

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
    error: str | None = None
    pid: int = 0
    started: float = 0.0
    finished: float = 0.0
    report: Any = None
    extra: dict[str, Any] = field(default_factory=dict)


def _template_fields(path: Path, index: int) -> dict[str, Any]:
    return {"stem": path.stem, "name": path.name, "parent": str(path.parent),
            "index": index, "ext": path.suffix.lstrip(".")}


def _default_extension(command: str, first_input: str) -> str:
    if command in DEFAULT_EXTENSIONS:
        return DEFAULT_EXTENSIONS[command]
    suffix = Path(first_input).suffix.lower()
    return suffix if suffix in (".obj", ".off", ".ply", ".stl", ".glb") else ".obj"


def plan_items(command: str, inputs: Sequence[str], output: str | None,
               t_values: Sequence[float] | None = None) -> list[Item]:
    """The items of a command line: inputs grouped (pairs for blend) and outputs named."""
    groups = [list(inputs)] if command == "blend" else [[p] for p in inputs]
    if command == "blend" and len(inputs) != 2:
        raise UsageError("blend takes exactly two meshes with the same faces: A B")
    if output is None:
        if command != "check":
            raise UsageError(f"{command} needs -o OUTPUT (a file, a template with {{stem}}, "
                             "or a folder)")
        return [Item(i, g, []) for i, g in enumerate(groups)]
    templated = "{" in output
    folder = output.endswith(("/", os.sep)) or Path(output).is_dir()
    many_t = t_values is not None and len(t_values) > 1
    if folder and not templated:
        output = str(Path(output) / ("{stem}" + ("-{t}" if many_t else "")
                                     + _default_extension(command, groups[0][0])))
    elif not templated and len(groups) > 1:
        raise UsageError(f"{len(groups)} inputs cannot all be written to {output}: use a "
                         "template such as -o 'out/{stem}.glb' or a folder")
    elif not templated and many_t:
        raise UsageError("several -t values need a template with {t} or {index} in -o")
    items, seen = [], {}
    for i, group in enumerate(groups):
        fields = _template_fields(Path(group[0]), i)
        try:
            if many_t:
                outs = [output.format(**fields, t=f"{t:g}") for t in t_values or []]
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


# ------------------------------------------------------------------------ operations


def _refinement_columns(row: Row, report: dict[str, Any] | None) -> None:
    refinement = (report or {}).get("refinement")
    if isinstance(refinement, list):  # a blend of several t: the worst
        refinement = max(refinement, key=lambda r: ((r or {}).get("after") or {}).get(
            "length_error", {}).get("max", 0.0), default=None)
    if not isinstance(refinement, dict):
        return
    row.refined = bool(refinement.get("refined"))
    after = refinement.get("after") or {}
    row.length_error = (after.get("length_error") or {}).get("max")
    row.angle_error = (after.get("angle_error") or {}).get("max")


def _mesh_options(args: argparse.Namespace, *, orthonormalize_default: bool = False
                  ) -> dict[str, Any]:
    options = {"frame_weight": args.frame_weight, "weighting": args.weighting,
               "solver": args.solver, "max_seconds": args.max_seconds, "refine": args.refine}
    if args.orthonormalize is not None and args.orthonormalize != orthonormalize_default:
        options["orthonormalize"] = args.orthonormalize
    return {k: v for k, v in options.items() if v is not None}


def _forms_of(backend: Any, path: str, args: argparse.Namespace, progress: Any) -> Any:
    from ffs import files

    if files.is_forms_file(path):
        return files.read_forms(path)
    vertices, faces = files.read_mesh(path, args.input_format)
    return backend.fundamental_forms(vertices, faces, progress=progress)


def run_forms(backend: Any, item: Item, args: argparse.Namespace, progress: Any, row: Row
              ) -> None:
    from ffs import files

    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    forms = backend.fundamental_forms(vertices, faces, progress=progress)
    out = Path(item.outputs[0])
    fmt = _output_format(out, args, ("json", "npz"))
    files.write_arrays(out, fmt, forms.arrays(), {})
    row.faces = len(forms.faces)
    row.note = f"{len(forms.edges)} edges"


def run_check(backend: Any, item: Item, args: argparse.Namespace, progress: Any, row: Row
              ) -> None:
    from ffs import files

    forms = _forms_of(backend, item.inputs[0], args, progress)
    report = backend.check_integrability(forms, tol=args.tolerance, progress=progress)
    row.faces, row.report = len(forms.faces), report.report
    row.extra = {"integrable": report.integrable, "max_defect": report.max_defect}
    row.note = ("integrable" if report.integrable else "NOT integrable") + \
        f", max defect {report.max_defect:.3g}"
    if item.outputs:
        out = Path(item.outputs[0])
        files.write_arrays(out, _output_format(out, args, ("json",)), {}, report.report)
    if args.require_integrable and not report.integrable:
        worst = (report.report.get("worst_vertices") or [None])[0]
        raise RunFailedError(f"the forms are not integrable: max defect {report.max_defect:.3g} "
                       f"(tolerance {args.tolerance or 1e-8:g}); worst vertex {worst}")


def run_reconstruct(backend: Any, item: Item, args: argparse.Namespace, progress: Any,
                    row: Row) -> None:
    from ffs import files

    forms = _forms_of(backend, item.inputs[0], args, progress)
    options = _mesh_options(args)
    options.update({k: v for k, v in {"tolerance": args.tolerance,
                                      "require_integrable": args.require_integrable or None
                                      }.items() if v is not None})
    constraints = files.read_json(args.constraints) if args.constraints else None
    result = backend.reconstruct(forms, constraints=constraints, progress=progress, **options)
    _write_mesh_result(item, args, row, result.vertices, result.faces, result.report)


def run_deform(backend: Any, item: Item, args: argparse.Namespace, progress: Any, row: Row
               ) -> None:
    from ffs import files

    handles = files.read_handles(args.handles)
    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    result = backend.deform(vertices, faces, handles.vertices, handles.positions,
                            rotation_handles=handles.rotation_faces or None,
                            handle_rotations=handles.rotations, roi=handles.roi,
                            progress=progress, **_mesh_options(args))
    _write_mesh_result(item, args, row, result.vertices, result.faces, result.report)


def run_flatten(backend: Any, item: Item, args: argparse.Namespace, progress: Any, row: Row
                ) -> None:
    import numpy as np

    from ffs import files

    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    result = backend.parameterize(vertices, faces, progress=progress,
                                  **_mesh_options(args, orthonormalize_default=True))
    out = Path(item.outputs[0])
    fmt = _output_format(out, args)
    if fmt in files.DATA_FORMATS:
        files.write_arrays(out, fmt, {"uv": result.uv, "flipped_faces": result.flipped_faces,
                                      "faces": np.asarray(faces)}, {"report": result.report})
    else:
        flat = np.column_stack([result.uv, np.zeros(len(result.uv))])
        files.write_mesh(out, fmt, flat, np.asarray(faces))
    row.faces, row.report = len(faces), result.report
    row.note = f"{len(result.flipped_faces)} flipped faces"
    _refinement_columns(row, result.report)


def run_blend(backend: Any, item: Item, args: argparse.Namespace, progress: Any, row: Row
              ) -> None:
    from ffs import files

    vertices_a, faces = files.read_mesh(item.inputs[0], args.input_format)
    vertices_b, _ = files.read_mesh(item.inputs[1], args.input_format)
    options = _mesh_options(args)
    options.pop("orthonormalize", None)
    t = args.t[0] if len(args.t) == 1 else list(args.t)
    result = backend.interpolate(vertices_a, vertices_b, faces, t, progress=progress,
                                 **options)
    shapes = [result.vertices] if len(args.t) == 1 else list(result.vertices)
    for out, vertices in zip(item.outputs, shapes, strict=True):
        files.write_mesh(Path(out), _output_format(Path(out), args), vertices, result.faces,
                         {"t": result.t, "refinement": result.refinement})
    row.faces, row.report = len(result.faces), {"refinement": result.refinement}
    row.note = "t = " + ", ".join(f"{x:g}" for x in args.t)
    _refinement_columns(row, row.report)


def run_convert(backend: Any, item: Item, args: argparse.Namespace, progress: Any, row: Row
                ) -> None:
    from ffs import files

    vertices, faces = files.read_mesh(item.inputs[0], args.input_format)
    mesh = backend.mesh(vertices, faces, progress=progress)
    out = Path(item.outputs[0])
    files.write_mesh(out, _output_format(out, args), mesh.vertices, mesh.faces, mesh.report)
    row.faces, row.report = len(mesh.faces), mesh.report
    row.note = f"{len(mesh.vertices)} vertices"


RUNNERS: dict[str, Callable[..., None]] = {
    "forms": run_forms, "check": run_check, "reconstruct": run_reconstruct,
    "deform": run_deform, "flatten": run_flatten, "blend": run_blend, "convert": run_convert}


class RunFailedError(Exception):
    """A file's run failed for a reason that is not an input error of the library
    (e.g. ``check --require-integrable``)."""


def _output_format(path: Path, args: argparse.Namespace,
                   allowed: Sequence[str] | None = None) -> str:
    from ffs import files

    fmt = (args.format or path.suffix.lstrip(".")).lower()
    writable = allowed or ("obj", "off", "ply", "stl", "glb", "json", "npz")
    if fmt not in writable:
        raise files.InputFileError(path, f"cannot write {fmt or '(no extension)'!r} here; "
                                   f"use one of {', '.join(writable)} (or --format)")
    return fmt


def _write_mesh_result(item: Item, args: argparse.Namespace, row: Row, vertices: Any,
                       faces: Any, report: dict[str, Any]) -> None:
    from ffs import files

    out = Path(item.outputs[0])
    files.write_mesh(out, _output_format(out, args), vertices, faces, report)
    row.faces, row.report = len(faces), report
    _refinement_columns(row, report)


_NUMPY_SCALAR = re.compile(r"\bnp\.(?:float|int|uint|bool_?)\d*\(([^()]*)\)")


def describe_error(exc: BaseException) -> str:
    """One line for a failed file: the problem's detail and where it points."""
    from ffs.files import InputFileError

    if isinstance(exc, InputFileError | RunFailedError | UsageError):
        return str(exc)
    try:
        from solver.errors import SolverInputError
        from solver.io import MeshFileError
    except ImportError:  # pragma: no cover - the client without the library
        SolverInputError = MeshFileError = ()  # type: ignore[assignment,misc]
    if isinstance(exc, SolverInputError):  # numpy scalar reprs as numbers, as the service
        return _NUMPY_SCALAR.sub(r"\1", f"{exc} ({exc.kind})")
    if isinstance(exc, MeshFileError):
        return exc.reason
    from ffs.errors import FFSError, ProblemError

    if isinstance(exc, ProblemError):
        where = ""
        first = exc.errors[0] if exc.errors else {}
        if first.get("field") and not exc.detail.startswith(str(first["field"])):
            index = first.get("index")
            where = f"{first['field']}" + (f"[{index}]" if index is not None else "") + ": "
        return f"{where}{exc.detail} ({exc.kind})"
    if isinstance(exc, FFSError):
        return str(exc)
    if isinstance(exc, MemoryError):
        return "out of memory"
    if isinstance(exc, OSError):
        return f"{exc.filename or ''}: {exc.strerror or exc}".lstrip(": ")
    return f"unexpected error ({type(exc).__name__}: {exc}); run with -v for the traceback"


def _is_expected(exc: BaseException) -> bool:
    from ffs.errors import FFSError
    from ffs.files import InputFileError

    expected: tuple[type[BaseException], ...] = (InputFileError, RunFailedError, FFSError, OSError,
                                                 MemoryError)
    try:
        from solver.errors import SolverInputError
        from solver.io import MeshFileError

        expected += (SolverInputError, MeshFileError)
    except ImportError:  # pragma: no cover
        pass
    return isinstance(exc, expected)


def run_item(command: str, args: argparse.Namespace, item: Item, backend: Any,
             events: Any, stop: threading.Event | None = None) -> Row:
    """Run one item and return its row (failures included: never raises for bad input)."""
    row = Row(file=item.name, outputs=item.outputs, path=" + ".join(item.inputs),
              pid=os.getpid(), started=time.time())
    events.put((item.index, "start", 0.0))

    def progress(stage: str, fraction: float) -> None:
        if stop is not None and stop.is_set():
            raise StoppedError("stopped")
        events.put((item.index, stage, float(fraction)))

    clock = time.perf_counter()
    try:
        RUNNERS[command](backend, item, args, progress, row)
    except StoppedError:
        row.status, row.error = "stopped", "stopped before it finished"
    except Exception as exc:
        row.status, row.error = "failed", describe_error(exc)
        for path in item.inputs:  # the line starts with the file already
            row.error = row.error.removeprefix(f"{path}: ")
        if args.verbose and not _is_expected(exc):
            row.extra["traceback"] = traceback.format_exc()
    row.seconds = time.perf_counter() - clock
    row.finished = time.time()
    return row


# --------------------------------------------------------------------- process pool

_WORKER: dict[str, Any] = {}


def _init_worker(events: Any) -> None:
    """A local worker process: progress goes to ``events``; Ctrl-C is the parent's."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _WORKER["events"] = events
    from ffs.local import Local

    _WORKER["backend"] = Local()


def _worker_run(command: str, args: argparse.Namespace, item: Item) -> Row:
    return run_item(command, args, item, _WORKER["backend"], _WORKER["events"])


# -------------------------------------------------------------------------- display


class Display:
    """Per-file progress bars with the current stage (rich, on a terminal only)."""

    def __init__(self, enabled: bool, total: int) -> None:
        self.progress: Any = None
        self.tasks: dict[int, Any] = {}
        self.names: dict[int, str] = {}
        if not enabled:
            return
        try:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )
        except ImportError:  # the progress library is optional: no bars then
            return
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn() if total > 1 else TextColumn(""),
                                 TimeElapsedColumn(), console=Console(stderr=True),
                                 transient=True)
        self.overall = self.progress.add_task("all files", total=total) if total > 1 else None
        self.progress.start()

    def name(self, index: int, name: str) -> None:
        self.names[index] = name

    def event(self, index: int, stage: str, fraction: float) -> None:
        if self.progress is None:
            return
        label = f"{self.names.get(index, index)} [cyan]{stage}[/]"
        if index not in self.tasks:
            self.tasks[index] = self.progress.add_task(label, total=1.0)
        self.progress.update(self.tasks[index], description=label, completed=fraction)

    def done(self, index: int) -> None:
        if self.progress is None:
            return
        if index in self.tasks:
            self.progress.remove_task(self.tasks.pop(index))
        if self.overall is not None:
            self.progress.advance(self.overall)

    def close(self) -> None:
        if self.progress is not None:
            self.progress.stop()


# --------------------------------------------------------------------------- batch


def _backend(args: argparse.Namespace) -> Any:
    if args.server:
        from ffs.client import Client

        return Client(args.server, timeout=args.timeout)
    from ffs.local import Local

    return Local()


def run_batch(command: str, args: argparse.Namespace, items: list[Item]) -> list[Row]:
    """Every item, ``args.jobs`` at a time, with progress; rows in input order."""
    display = Display(sys.stderr.isatty() and not args.quiet, len(items))
    for item in items:
        display.name(item.index, item.name)
    rows: dict[int, Row] = {}
    stop = threading.Event()
    pool: futures.Executor
    if args.server or args.jobs == 1:
        events: Any = queue.Queue()
        backend = _backend(args)
        pool = futures.ThreadPoolExecutor(max_workers=args.jobs)
        pending = {pool.submit(run_item, command, args, item, backend, events, stop): item
                   for item in items}
    else:
        context = multiprocessing.get_context("spawn")
        events = context.Queue()
        pool = futures.ProcessPoolExecutor(max_workers=args.jobs, mp_context=context,
                                           initializer=_init_worker, initargs=(events,))
        pending = {pool.submit(_worker_run, command, args, item): item for item in items}
    try:
        while pending:
            done, _ = futures.wait(pending, timeout=0.05, return_when=futures.FIRST_COMPLETED)
            _drain(events, display)
            for future in done:
                item = pending.pop(future)
                rows[item.index] = _row_of(future, item)
                display.done(item.index)
                if rows[item.index].status == "failed" and args.fail_fast and not stop.is_set():
                    stop.set()
                    for other in pending:
                        other.cancel()
            if stop.is_set():
                for future in [f for f in pending if f.cancelled()]:
                    item = pending.pop(future)
                    rows[item.index] = Row(item.name, item.outputs, status="skipped",
                                           error="not run (--fail-fast)")
        _drain(events, display)
    except KeyboardInterrupt:
        stop.set()  # jobs on a server notice it at their next poll and are cancelled
        display.close()
        pool.shutdown(wait=False, cancel_futures=True)
        for process in list((getattr(pool, "_processes", None) or {}).values()):
            process.terminate()  # local workers: their solves are of no use any more
        futures.wait(pending, timeout=5)
        raise
    finally:
        display.close()
    pool.shutdown(wait=True)
    return [rows[item.index] for item in items]


def _row_of(future: futures.Future[Row], item: Item) -> Row:
    try:
        return future.result()
    except futures.CancelledError:
        return Row(item.name, item.outputs, status="skipped", error="not run (--fail-fast)")
    except Exception as exc:  # a worker process that died (killed, out of memory)
        return Row(item.name, item.outputs, status="failed",
                   error=f"the worker running it failed: {describe_error(exc)}")


def _drain(events: Any, display: Display) -> None:
    while True:
        try:
            index, stage, fraction = events.get_nowait()
        except queue.Empty:
            return
        display.event(index, stage, fraction)


# ------------------------------------------------------------------------- summary


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.2e}"


def print_summary(command: str, rows: list[Row], elapsed: float, quiet: bool) -> None:
    """The table (file, faces, seconds, refined, residuals, status) and a total line."""
    failed = [r for r in rows if r.status != "ok"]
    for row in failed:
        if row.status == "failed":
            print(f"ffs {command}: {row.path or row.file}: {row.error}", file=sys.stderr)
            if row.extra.get("traceback"):
                print(row.extra["traceback"], file=sys.stderr, end="")
    if quiet:
        return
    headers = ["file", "faces", "seconds", "refined", "length err", "angle err", "result"]
    table = [[r.file, "-" if r.faces is None else str(r.faces), f"{r.seconds:.3f}",
              "-" if r.refined is None else ("yes" if r.refined else "no"),
              _number(r.length_error), _number(r.angle_error),
              (r.note or "ok") if r.status == "ok" else r.status.upper()] for r in rows]
    total = (f"{len(rows) - len(failed)} of {len(rows)} done, {len(failed)} failed "
             f"in {elapsed:.2f} s")
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:
        widths = [max(len(h), *(len(r[i]) for r in table)) for i, h in enumerate(headers)]
        for line in [headers, *table]:
            print("  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)))
        print(total)
        return
    console = Console(highlight=False, width=None if sys.stdout.isatty() else 1000)
    grid = Table(*headers, box=None, pad_edge=False, show_edge=False)
    for line, row in zip(table, rows, strict=True):
        style = None if row.status == "ok" else "red"
        grid.add_row(*line, style=style)
    console.print(grid)
    console.print(total)


def write_report(path: str, command: str, args: argparse.Namespace, rows: list[Row],
                 elapsed: float) -> None:
    from ffs.files import json_text

    document = {
        "command": command, "version": __version__, "server": args.server,
        "jobs": args.jobs, "seconds": elapsed,
        "files": [{"file": r.file, "outputs": r.outputs, "status": r.status,
                   "error": r.error, "faces": r.faces, "seconds": r.seconds,
                   "refined": r.refined, "length_error": r.length_error,
                   "angle_error": r.angle_error, "pid": r.pid, "started": r.started,
                   "finished": r.finished, **r.extra, "report": r.report} for r in rows]}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json_text(document))


# -------------------------------------------------------------------------- parsing


class _Parser(argparse.ArgumentParser):
    """argparse that says ``ffs <command>: error: ...`` and exits 2 (usage)."""

    def error(self, message: str) -> Any:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    common = _Parser(add_help=False)
    io = common.add_argument_group("files")
    io.add_argument("-o", "--output", help="output file, template ({stem}, {name}, {parent}, "
                    "{index}, {t}) or folder")
    io.add_argument("--format", help="output format instead of the extension: obj, off, ply, "
                    "stl, glb, json, npz")
    io.add_argument("--input-format", help="input mesh format instead of the extension")
    io.add_argument("--report", metavar="FILE", help="write every file's full report (JSON)")
    run = common.add_argument_group("running")
    run.add_argument("-j", "--jobs", type=_positive_int, default=1,
                     help="files at once: local worker processes, or concurrent jobs on "
                     "the server (default 1)")
    run.add_argument("--threads", type=_positive_int, help="BLAS/MKL threads per local worker "
                     "(default: cores / jobs)")
    run.add_argument("--server", default=os.environ.get("FFS_SERVER") or None, metavar="URL",
                     help="run on this service (default $FFS_SERVER; none: in-process)")
    run.add_argument("--local", dest="server", action="store_const", const=None,
                     help="run in-process even if FFS_SERVER is set")
    run.add_argument("--timeout", type=_positive_float, default=60.0,
                     help="seconds for each answer of the server (default 60)")
    run.add_argument("--fail-fast", action="store_true", help="stop at the first failure")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress, no summary; "
                     "only errors")
    run.add_argument("-v", "--verbose", action="store_true",
                     help="tracebacks of unexpected errors")

    solve = _Parser(add_help=False)
    group = solve.add_argument_group("solver options (named like the HTTP options)")
    group.add_argument("--refine", dest="refine", action="store_true", default=None,
                       help="always refine to the nearest surface when not exact")
    group.add_argument("--no-refine", dest="refine", action="store_false",
                       help="the linear answer (Eq. 5) only")
    group.add_argument("--max-seconds", type=_positive_float,
                       help="wall-clock budget of the refinement")
    group.add_argument("--orthonormalize", dest="orthonormalize", action="store_true",
                       default=None, help="second solve with orthonormalized frames")
    group.add_argument("--no-orthonormalize", dest="orthonormalize", action="store_false")
    group.add_argument("--frame-weight", type=_positive_float)
    group.add_argument("--weighting", choices=("uniform", "cotan", "cotan_clamped"))
    group.add_argument("--solver", choices=("auto", "pardiso", "cholespy", "superlu"),
                       help="sparse factorization backend")

    tolerance = _Parser(add_help=False)
    tolerance.add_argument("--tolerance", type=_positive_float,
                           help="integrability tolerance (default 1e-8)")
    tolerance.add_argument("--require-integrable", action="store_true",
                           help="fail (exit 1) when the forms are not integrable")

    parser = _Parser(prog="ffs", description="Fundamental forms of triangle meshes: forms, "
                     "integrability, reconstruction, deformation, flattening, blending; "
                     "in-process or on a service (--server).",
                     epilog="Exit codes: 0 done, 1 a file failed, 2 usage. "
                     "Example: ffs reconstruct forms/*.npz -o out/{stem}.glb -j 2")
    parser.add_argument("--version", action="version", version=f"ffs {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="command", required=True,
                                     parser_class=_Parser)
    meshes = {"nargs": "+", "metavar": "MESH"}
    commands.add_parser("forms", parents=[common], help="edge lengths and dihedral angles "
                        "(.json or .npz)").add_argument("inputs", **meshes)
    check = commands.add_parser("check", parents=[common, tolerance],
                                help="integrability of forms or meshes")
    check.add_argument("inputs", nargs="+", metavar="FORMS_OR_MESH")
    rebuild = commands.add_parser("reconstruct", parents=[common, solve, tolerance],
                                  help="a mesh from forms (or from a mesh's own forms)")
    rebuild.add_argument("inputs", nargs="+", metavar="FORMS_OR_MESH")
    rebuild.add_argument("--constraints", metavar="FILE", help="JSON constraints as the API "
                         "takes them: {\"positions\": [...], \"frames\": [...]}")
    deform = commands.add_parser("deform", parents=[common, solve], help="move handles")
    deform.add_argument("inputs", **meshes)
    deform.add_argument("--handles", required=True, metavar="FILE", help="JSON: "
                        "[{\"vertex\": i, \"position\": [x, y, z]}, ...] or {\"handles\", "
                        "\"rotations\", \"roi\"}")
    commands.add_parser("flatten", parents=[common, solve], help="flatten meshes with "
                        "boundary (uv as z = 0 meshes, or .json/.npz)").add_argument(
                            "inputs", **meshes)
    blend = commands.add_parser("blend", parents=[common, solve],
                                help="blend two meshes with the same faces in form space")
    blend.add_argument("inputs", nargs="+", metavar="MESH", help="A and B")
    blend.add_argument("-t", "--t", type=float, nargs="+", default=[0.5],
                       help="blend value(s): 0 gives A, 1 gives B (default 0.5)")
    commands.add_parser("convert", parents=[common], help="read, check and write meshes "
                        "(formats from the extensions)").add_argument("inputs", **meshes)
    serve = commands.add_parser("serve", help="run the service (python -m service)")
    serve.add_argument("--host", help="bind address (FFS_HOST, default 127.0.0.1)")
    serve.add_argument("--port", type=int, help="port (FFS_PORT, default 8000)")
    serve.add_argument("--workers", type=_positive_int, help="worker processes (FFS_WORKERS)")
    return parser


def _set_threads(args: argparse.Namespace) -> None:
    """BLAS/MKL threads per worker, set before numpy or MKL load (they read these once)."""
    threads = args.threads
    if threads is None and not args.server and args.jobs > 1:
        threads = max(1, (os.cpu_count() or 1) // args.jobs)
    if threads is not None:
        for name in THREAD_VARIABLES:
            os.environ[name] = str(threads)


def serve(args: argparse.Namespace) -> int:
    for name, value in (("FFS_HOST", args.host), ("FFS_PORT", args.port),
                        ("FFS_WORKERS", args.workers)):
        if value is not None:
            os.environ[name] = str(value)
    from service.__main__ import main as serve_main

    serve_main()
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    args = build_parser().parse_args(argv)
    if args.command == "serve":
        return serve(args)
    try:
        items = plan_items(args.command, args.inputs, args.output,
                           args.t if args.command == "blend" else None)
    except UsageError as exc:
        print(f"ffs {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.command == "blend" and args.orthonormalize is not None:
        print("ffs blend: error: blend takes no --orthonormalize (a blend is reconstructed "
              "from blended forms)", file=sys.stderr)
        return EXIT_USAGE
    args.jobs = min(args.jobs, len(items))
    _set_threads(args)
    started = time.perf_counter()
    try:
        rows = run_batch(args.command, args, items)
    except KeyboardInterrupt:
        print(f"ffs {args.command}: interrupted", file=sys.stderr)
        sys.stderr.flush()
        os._exit(EXIT_INTERRUPTED)
    elapsed = time.perf_counter() - started
    print_summary(args.command, rows, elapsed, args.quiet)
    if args.report:
        write_report(args.report, args.command, args, rows, elapsed)
    return EXIT_OK if all(r.status == "ok" for r in rows) else EXIT_FAILED


def console_main() -> None:
    """The ``ffs`` console script."""
    sys.exit(main())
