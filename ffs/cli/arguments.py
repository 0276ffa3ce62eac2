"""The command line's arguments: the subcommands and their options, and argparse's usage
errors as exit code 2."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from ffs import __version__
from ffs.operations import COMMANDS

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
"""Exit codes: all done, a file failed, usage, interrupted (Ctrl-C)."""


class _Parser(argparse.ArgumentParser):
    """argparse that says ``ffs <command>: error: ...`` and exits 2 (usage)."""

    def error(self, message: str) -> Any:  # type: ignore[override]
        """Print the usage and ``message``; exit :data:`EXIT_USAGE`."""
        self.print_usage(sys.stderr)
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def _positive_int(text: str) -> int:
    """argparse type: an integer of at least 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    """argparse type: a number greater than 0."""
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``ffs`` parser: one subcommand per operation, plus ``serve``.

    Returns:
        The parser; ``parse_args`` exits 2 with ``ffs <command>: error: ...`` on bad usage.
    """
    common = _Parser(add_help=False)
    io = common.add_argument_group("files")
    io.add_argument("-o", "--output", help="output file, template ({stem}, {name}, {parent}, "
                    "{index}, {t}) or folder")
    io.add_argument("--format", help="output format instead of the extension: obj, off, ply, "
                    "stl, glb, gltf, json, npz")
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
    run.add_argument("--token", default=os.environ.get("FFS_TOKEN") or None, metavar="KEY",
                     help="API key of a service with keys (default $FFS_TOKEN, which keeps "
                     "it out of the process list)")
    run.add_argument("--local", dest="server", action="store_const", const=None,
                     help="run in-process even if FFS_SERVER is set")
    run.add_argument("--timeout", type=_positive_float, default=60.0,
                     help="seconds for each answer of the server (default 60)")
    run.add_argument("--fail-fast", action="store_true", help="stop at the first failure")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress, no summary; "
                     "only errors")
    run.add_argument("-v", "--verbose", action="store_true",
                     help="tracebacks of unexpected errors")
    run.add_argument("--strict", action="store_true",
                     help="exit 1 when an answer carries a warning (past a documented "
                     "threshold: flipped faces, length or angle error, a time limit with "
                     "no progress)")

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
    tolerance.add_argument("--linear-solver", choices=("auto", "direct", "iterative"),
                           help="Eq. 5's linear solve: direct (factorization), iterative "
                           "(multigrid-preconditioned CG, bounded memory) or auto (default: "
                           "iterative where the factor would not fit; docs/large-meshes.md)")

    parser = _Parser(prog="ffs", description="Fundamental forms of triangle meshes: forms, "
                     "integrability, reconstruction, deformation, flattening, blending; "
                     "in-process or on a service (--server).",
                     epilog="Exit codes: 0 done, 1 a file failed (or, with --strict, an "
                     "answer carries a warning), 2 usage. "
                     "Example: ffs reconstruct forms/*.npz -o out/{stem}.glb -j 2. "
                     "Meshes as they come: polygons (OBJ, OFF, PLY) are fan-triangulated and "
                     "answers are on those triangles; a non-manifold mesh (an edge of 3 or "
                     "more faces, a vertex joining two fans) is solved on its manifold cut and "
                     "answered per file vertex (copies averaged, spread in the report); forms "
                     "files keep the cut's vertex_map and each part's placement, so "
                     "reconstruct puts every part back where it was (without a placement "
                     "parts are laid side by side); angles outside (-pi, pi] are wrapped and "
                     "counted; a face of zero area (collinear corners) gets its neighbours' "
                     "mean normal and is counted (report input.zero_area_faces); vertices "
                     "joined by an edge of length ~0 (1e-12 of the diagonal) are welded into "
                     "the lowest index and the faces that collapse (or repeat an index) are "
                     "dropped, answers keep the file's numbering (report input.weld; forms "
                     "files keep weld_map and dropped_faces); the "
                     "endpoints of needle edges move as one in a refinement. "
                     "See docs/service.md#meshes-as-they-come.")
    parser.add_argument("--version", action="version", version=f"ffs {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="command", required=True,
                                     parser_class=_Parser)
    groups = {"solve": solve, "tolerance": tolerance}
    sub: dict[str, argparse.ArgumentParser] = {}
    for command in COMMANDS.values():  # one subcommand per row of the table
        sub[command.name] = commands.add_parser(
            command.name, help=command.help,
            parents=[common, *(groups[g] for g in command.groups)])
        sub[command.name].add_argument("inputs", nargs=command.nargs, metavar=command.inputs,
                                       help=command.inputs_help or None)
    _command_options(sub)
    serve = commands.add_parser("serve", help="run the service (python -m service)")
    serve.add_argument("--host", help="bind address (FFS_HOST, default 127.0.0.1)")
    serve.add_argument("--port", type=int, help="port (FFS_PORT, default 8000)")
    serve.add_argument("--workers", type=_positive_int, help="worker processes (FFS_WORKERS)")
    return parser


def _command_options(sub: dict[str, argparse.ArgumentParser]) -> None:
    """The options one command has (the table's :class:`~ffs.operations.Command` gives
    each its common ones)."""
    for name in ("reconstruct", "vjp"):
        sub[name].add_argument("--constraints", metavar="FILE", help="JSON constraints as "
                               "the API takes them: {\"positions\": [...], \"frames\": [...]}")
    sub["reconstruct"].add_argument(
        "--align-to", metavar="REF", help="move the answer rigidly onto this mesh (same "
        "vertices; e.g. the mesh the forms came from) and report the residual")
    sub["vjp"].add_argument("--cotangent", required=True, metavar="FILE",
                            help="the gradient of a loss with respect to the reconstructed "
                            "vertices: (n, 3) or (k, n, 3) in .npy, .npz (array "
                            "\"cotangent\") or .json ([[x, y, z], ...] or {\"cotangent\": "
                            "...})")
    sub["deform"].add_argument("--handles", required=True, metavar="FILE", help="JSON: "
                               "[{\"vertex\": i, \"position\": [x, y, z]}, ...] or "
                               "{\"handles\", \"rotations\", \"roi\"}; or a Botsch-Sorkine "
                               "NAME.sel (0 fixed, 1 free, 2 handle per vertex) with NAME.def "
                               "(4x4 transform) beside it")
    flatten = sub["flatten"]
    flatten.add_argument("--seams", choices=("auto", "none"), default=None,
                         help="auto (default): cut into charts where needed; none: one "
                         "chart per component, closed meshes refused")
    flatten.add_argument("--flat", action="store_true", help="write the flat layout "
                         "(u, v, 0) to .obj/.glb too, instead of the mesh with its uv")
    blend = sub["blend"]
    blend.add_argument("-t", "--t", type=float, nargs="+", default=None,
                       help="two meshes: blend value(s): 0 gives A, 1 gives B, 1.5 "
                       "extrapolates (default 0.5)")
    blend.add_argument("--weights", metavar="FILE", help="JSON rows of affine weights, one "
                       "per mesh ([[w1, ..., wK], ...], or {\"weights\": rows, \"times\": "
                       "seconds}); each row is a shape")
    blend.add_argument("--rows-per-second", type=_positive_float, default=24.0,
                       help="playback rate of an animated .glb (default 24)")
    blend.add_argument("--independent", action="store_true", help="solve every row on its "
                       "own (default: as a sequence, each row from its neighbour)")
