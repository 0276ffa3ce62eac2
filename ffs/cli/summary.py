"""After the batch: the failures on stderr, the summary table on stdout, and ``--report``'s
JSON document with every file's full report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ffs import __version__
from ffs.cli.items import Row


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.2e}"


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
    """Write ``--report``: the run's settings and every row with its full report (JSON)."""
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
