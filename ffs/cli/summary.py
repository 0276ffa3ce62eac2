"""After the batch: the failures on stderr, the summary table on stdout, and ``--report``'s
JSON document with every file's full report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ffs import __version__
from ffs.cli.items import Row


def _percent(value: float | None) -> str:
    """A relative error (a fraction) as a percentage: ``0.0123`` -> ``1.23%``."""
    return "-" if value is None else f"{100 * value:.3g}%"


def _radians(value: float | None) -> str:
    """An angle error in radians, with degrees: ``2.25`` -> ``2.25 rad (129°)``."""
    import math

    return "-" if value is None else f"{value:.3g} rad ({math.degrees(value):.3g}°)"


ERROR_STATISTIC = {"flatten": "mean"}
"""The statistic of the error columns where it is not the largest error: a flattening's
columns are its mean edge-length and corner-angle changes, the statistics its
``length-distortion`` and ``angle-distortion`` warnings are on."""


def error_headers(command: str) -> list[str]:
    """The two error columns' headers of ``command``'s table, labelled with their statistic
    (:data:`ERROR_STATISTIC`; the largest error unlabelled)."""
    statistic = ERROR_STATISTIC.get(command)
    suffix = f" ({statistic})" if statistic else ""
    return [f"length err{suffix}", f"angle err{suffix}"]


def _refined_cell(row: Row) -> str:
    """The ``refined`` cell: the outcome with its stop reason, else yes/no/-."""
    if row.outcome:
        return row.outcome
    return "-" if row.refined is None else ("yes" if row.refined else "no")


def _result_cell(row: Row) -> str:
    """The ``result`` cell: ok (or the command's note), WARN with the warnings' codes (and
    the note: an --align-to residual or a flattening's charts stay in view), or the
    status."""
    if row.status != "ok":
        return row.status.upper()
    if row.warnings:
        codes = "WARN " + ", ".join(w.get("code", "?") for w in row.warnings)
        return f"{codes}; {row.note}" if row.note else codes
    return row.note or "ok"


def print_warnings(command: str, rows: list[Row]) -> None:
    """One line per warning on stderr: ``ffs <command>: <file>: warning: <message>``."""
    for row in rows:
        for warning in row.warnings:
            print(f"ffs {command}: {row.path or row.file}: warning: {warning.get('message')}",
                  file=sys.stderr)


def print_summary(command: str, rows: list[Row], elapsed: float, quiet: bool) -> None:
    """Print each failure's line, then the table and a total line.

    Args:
        command: The subcommand (prefix of the failure lines).
        rows: The items' rows, in input order.
        elapsed: Wall time of the batch, seconds.
        quiet: Failures only (``-q``).
    """
    failed = [r for r in rows if r.status != "ok"]
    for row in failed:
        if row.status == "failed":
            print(f"ffs {command}: {row.path or row.file}: {row.error}", file=sys.stderr)
            if row.extra.get("traceback"):
                print(row.extra["traceback"], file=sys.stderr, end="")
    print_warnings(command, rows)
    if quiet:
        return
    headers = ["file", "faces", "seconds", "refined", *error_headers(command), "result"]
    table = [[r.file, "-" if r.faces is None else str(r.faces), f"{r.seconds:.3f}",
              _refined_cell(r), _percent(r.length_error), _radians(r.angle_error),
              _result_cell(r)] for r in rows]
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
        style = "red" if row.status != "ok" else ("yellow" if row.warnings else None)
        grid.add_row(*line, style=style)
    console.print(grid)
    console.print(total)


def write_report(path: str, command: str, args: argparse.Namespace, rows: list[Row],
                 elapsed: float) -> None:
    """Write ``--report``: the run's settings and every row with its full report (JSON)."""
    from ffs.files import json_text

    document = {
        "command": command, "version": __version__, "server": args.server,
        "jobs": args.jobs, "seconds": elapsed,
        "files": [{"file": r.file, "outputs": r.outputs, "status": r.status,
                   "error": r.error, "faces": r.faces, "seconds": r.seconds,
                   "refined": r.refined, "length_error": r.length_error,
                   "angle_error": r.angle_error, "outcome": r.outcome,
                   "warnings": r.warnings, "pid": r.pid, "started": r.started,
                   "finished": r.finished, **r.extra, "report": r.report} for r in rows]}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json_text(document))
