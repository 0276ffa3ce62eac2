"""``ffs``: the command line. ``ffs <command> <inputs...> -o <output> [options]``.

Commands: ``forms`` (edge lengths and dihedral angles), ``check`` (integrability),
``reconstruct`` (a mesh from forms), ``vjp`` (its gradients for a cotangent of the
vertices), ``deform`` (handles), ``flatten`` (parameterize),
``blend`` (blend or extrapolate 1 to 64 meshes, one file per row or one animated GLB),
``mean`` (their form-space mean), ``transfer`` (a deformation applied to another mesh),
``convert`` (read, check, write), ``serve`` (runs the service, ``python -m service``).

* The commands and the operations each runs: :data:`ffs.operations.COMMANDS`.
* In-process through :mod:`solver` by default; ``--server URL`` (or ``FFS_SERVER``) runs the
  same work on a service through :class:`ffs.client.Client` (as jobs: stage progress, no
  request timeout).
* Many inputs at once: ``-o`` is a template (``{stem}``, ``{name}``, ``{parent}``,
  ``{index}``, ``{t}`` for blends) or a folder; ``-j N`` runs N at a time (local worker
  processes with ``cores / N`` BLAS threads each unless ``--threads``, or N concurrent jobs
  on the server); a failing file is reported and the rest carry on (``--fail-fast`` stops).
* A progress bar per running file with its stage (on a terminal; quiet otherwise or with
  ``-q``), then a summary table on stdout; ``--report FILE`` writes every file's full report.
* Exit codes: 0 all done, 1 a file failed (its message names the file, field and index)
  or, with ``--strict``, an answer carries a warning (``WARN`` in the table, one line per
  warning on stderr), 2 usage; 130 interrupted. Bad input never prints a traceback
  (``-v`` shows the traceback of an unexpected error).

Modules, in the order a run goes through them: :mod:`~ffs.cli.arguments` (the parser),
:mod:`~ffs.cli.items` (inputs and outputs of each unit of work), :mod:`~ffs.cli.batch`
(workers, ``-j``, ``--fail-fast``) running :mod:`~ffs.cli.commands` (one runner per
command) with :mod:`~ffs.cli.progress` (bars) and :mod:`~ffs.cli.failures` (one line per
failed file), then :mod:`~ffs.cli.summary` (table and ``--report``). None of them imports
numpy at import time: the BLAS thread variables are set first.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Sequence

from ffs.cli.arguments import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, build_parser
from ffs.cli.batch import run_batch
from ffs.cli.items import (
    UsageError,
    check_given_files,
    check_output_formats,
    check_server,
    check_shape_count,
    plan_items,
)
from ffs.cli.summary import print_summary, write_report

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
"""The BLAS/OpenMP thread variables ``--threads`` (or ``cores / jobs``) sets."""


def _set_threads(args: argparse.Namespace) -> None:
    """BLAS/MKL threads per worker, set before numpy or MKL load (they read these once)."""
    threads = args.threads
    if threads is None and not args.server and args.jobs > 1:
        threads = max(1, (os.cpu_count() or 1) // args.jobs)
    if threads is not None:
        for name in THREAD_VARIABLES:
            os.environ[name] = str(threads)


def serve(args: argparse.Namespace) -> int:
    """``ffs serve``: run the service as a program (``python -m service``, which this
    process becomes: signals reach uvicorn directly) with ``--host``/``--port``/
    ``--workers`` as its environment variables. The command line never imports the service."""
    env = dict(os.environ)
    for name, value in (("FFS_HOST", args.host), ("FFS_PORT", args.port),
                        ("FFS_WORKERS", args.workers)):
        if value is not None:
            env[name] = str(value)
    command = [sys.executable, "-m", "service"]
    sys.stdout.flush()
    sys.stderr.flush()
    if os.name == "nt":  # no exec on Windows: a child, its exit code ours
        return subprocess.call(command, env=env)
    os.execve(sys.executable, command, env)
    return EXIT_OK  # not reached


def _blend_rows(args: argparse.Namespace) -> list[float]:
    """The row labels of ``ffs blend`` (its ``-t`` values, or the row numbers of
    ``--weights``), after reading ``--weights`` into ``args.weights_rows`` and
    ``args.times``."""
    args.weights_rows, args.times = None, None
    if args.weights is not None:
        if args.t is not None:
            raise UsageError("give -t (two meshes) or --weights, not both")
        from ffs import files

        try:
            document = files.read_json(args.weights)
        except files.InputFileError as exc:
            raise UsageError(str(exc)) from None
        rows = document.get("weights") if isinstance(document, dict) else document
        args.times = document.get("times") if isinstance(document, dict) else None
        if (not isinstance(rows, list) or not rows
                or not all(isinstance(r, list) and len(r) == len(args.inputs) for r in rows)):
            raise UsageError(f"{args.weights}: expected rows of {len(args.inputs)} weights "
                             "(one per mesh): [[w1, ..., wK], ...]")
        args.weights_rows = rows
        return [float(k) for k in range(len(rows))]
    if len(args.inputs) != 2:
        count = len(args.inputs)
        raise UsageError(f"-t blends two meshes (A B), got {count}: "
                         f"{'one mesh takes' if count == 1 else f'{count} meshes take'} "
                         f"--weights (rows of {count} weight{'s' * (count > 1)})")
    args.t = args.t or [0.5]
    return list(args.t)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line.

    Args:
        argv: The arguments after ``ffs`` (default: ``sys.argv[1:]``).

    Returns:
        The exit code: 0 all done, 1 a file failed, 2 usage (Ctrl-C exits 130 at once).
    """
    args = build_parser().parse_args(argv)
    if args.command == "serve":
        return serve(args)
    try:
        rows = _blend_rows(args) if args.command == "blend" else None
        items = plan_items(args.command, args.inputs, args.output, rows,
                           getattr(args, "format", None))
        args.jobs = min(args.jobs, len(items))
        _set_threads(args)  # before the format check imports the library (numpy, MKL)
        check_shape_count(args.command, args.inputs)
        check_output_formats(args.command, items, args.format)
        check_given_files(args)
        check_server(args.server)
    except UsageError as exc:
        print(f"ffs {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.command == "blend" and args.orthonormalize is not None:
        print("ffs blend: error: blend takes no --orthonormalize (a blend is reconstructed "
              "from blended forms)", file=sys.stderr)
        return EXIT_USAGE
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
    if args.strict and any(r.warnings for r in rows):
        return EXIT_FAILED
    return EXIT_OK if all(r.status == "ok" for r in rows) else EXIT_FAILED


def console_main() -> None:
    """The ``ffs`` console script."""
    sys.exit(main())
