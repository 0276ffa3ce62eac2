"""The client's table of the service's operations: for each operation of the service's
registry (``service/operations.py``, ``POST /v1/{name}``), the :class:`~ffs.client.Client`
and :class:`~ffs.local.Local` method that runs it, its result type (:mod:`ffs.results`) and
the ``ffs`` commands that use it; and the table of the ``ffs`` commands.

What is derived from it: the client's operation methods (each ``<method>(...,
progress=None)`` runs its ``<method>_call`` builder, :mod:`ffs.client`: made from the row for
an operation that takes only arrays and options, hand-written otherwise), the
operations :meth:`~ffs.client.Client.submit` takes, each call's result decoder, the
command line's subcommands (:func:`ffs.cli.arguments.build_parser`) and their runners
(:data:`ffs.cli.commands.RUNNERS`). ``tests/client/test_operation_table.py`` fails when an
operation of the service has no entry here, no client method, no local method or no command.

Kept free of the service (no FastAPI): the names mirror the registry, they are not imported
from it; and of numpy (the command line reads it before it sets the BLAS thread variables):
result types are named, :meth:`Operation.decode` imports them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal


@dataclass(frozen=True)
class Operation:
    """One operation of the service as the client runs it.

    Attributes:
        name: the service's name (``POST /v1/{name}``, a job's ``operation``).
        method: the :class:`~ffs.client.Client` and :class:`~ffs.local.Local` method
            (named like the library's function); ``<method>_call`` builds its request.
        result: the name of its result type in :mod:`ffs.results`, whose ``from_dict``
            decodes the service's JSON answer.
        arrays: for an operation that takes only its large arrays (positional, in this
            order) and, with ``options``, the solver options: their names; its request is
            then built from this row (:func:`ffs.client.table_call`). Empty: the client
            writes ``<method>_call`` by hand (constraints, handles, weights, ...).
        options: it takes ``refine`` and the solver options (``{"options": {...}}``).
        summary: the method's docstring, for a request built from this row.
    """

    name: str
    method: str
    result: str
    arrays: tuple[str, ...] = ()
    options: bool = True
    summary: str = ""

    @property
    def decode(self) -> Callable[[dict[str, Any]], Any]:
        """The result type's ``from_dict``."""
        from ffs import results

        return getattr(results, self.result).from_dict  # type: ignore[no-any-return]


OPERATIONS: dict[str, Operation] = {op.name: op for op in (
    Operation("forms", "fundamental_forms", "Forms", ("vertices", "faces"), False,
              "Edge lengths and signed dihedral angles of a mesh (``POST /v1/forms``)."),
    Operation("integrability", "check_integrability", "Integrability"),
    Operation("reconstruct", "reconstruct", "Mesh"),
    Operation("reconstruct/vjp", "reconstruct_vjp", "VjpResult"),
    Operation("deform", "deform", "Mesh"),
    Operation("parameterize", "parameterize", "Parameterization", ("vertices", "faces"), True,
              "Flatten a mesh (``POST /v1/parameterize``): one chart, or charts cut along "
              "seams and packed (``result.texcoords``, ``uv_faces``, ``uv_vertex``, "
              "``face_chart``; ``options``: ``seams=\"auto\"|\"none\"``, "
              "``max_chart_distortion``)."),
    Operation("interpolate", "interpolate", "Blend"),
    Operation("blend", "blend", "ShapeBlend"),
    Operation("transfer", "transfer", "Mesh", ("source", "source_deformed", "target", "faces"),
              True, "``target`` deformed as ``source`` was into ``source_deformed`` (``POST "
              "/v1/transfer``; three embeddings of ``faces``)."),
    Operation("mesh", "mesh", "Mesh", ("vertices", "faces"), False,
              "A mesh checked like every operation checks it (``POST /v1/mesh``), its "
              "report."),
)}
"""Every operation of the service, by its name, in the registry's order."""


@dataclass(frozen=True)
class Command:
    """One ``ffs`` subcommand (its runner: ``ffs.cli.commands.run_<name>``).

    Attributes:
        name: the subcommand.
        operations: the operations it runs (:data:`OPERATIONS` names).
        help: its one-line help.
        inputs: the metavar of its input files.
        nargs: how many input files (argparse ``nargs``).
        inputs_help: the help of its input files (none: the metavar says it).
        groups: the option groups it takes besides the common ones: ``solve`` (the solver
            options), ``tolerance`` (integrability tolerance and ``--require-integrable``).
    """

    name: str
    operations: tuple[str, ...]
    help: str
    inputs: str = "MESH"
    nargs: int | Literal["+"] = "+"
    groups: tuple[str, ...] = ()
    inputs_help: str = ""


COMMANDS: dict[str, Command] = {command.name: command for command in (
    Command("forms", ("forms",), "edge lengths and dihedral angles (.json or .npz)"),
    Command("check", ("integrability", "forms"), "integrability of forms or meshes",
            "FORMS_OR_MESH", groups=("tolerance",)),
    Command("reconstruct", ("reconstruct", "forms"),
            "a mesh from forms (or from a mesh's own forms)", "FORMS_OR_MESH",
            groups=("solve", "tolerance")),
    Command("vjp", ("reconstruct/vjp", "forms"),
            "gradients of a reconstruction: a cotangent of the vertices pulled back to the "
            "lengths, angles and constraint targets (.json or .npz)", "FORMS_OR_MESH",
            groups=("solve", "tolerance")),
    Command("deform", ("deform",), "move handles", groups=("solve",)),
    Command("flatten", ("parameterize",),
            "flatten meshes (seams and a packed atlas where one chart does not do): "
            ".obj/.glb the mesh with its uv (vt, TEXCOORD_0), .ply/.off/.stl the flat layout "
            "(z = 0), .json/.npz the arrays", groups=("solve",)),
    Command("blend", ("interpolate", "blend"),
            "blend, extrapolate or animate meshes with the same faces in form space (A B "
            "with -t, or K meshes with --weights)",
            groups=("solve",), inputs_help="A and B (-t), or K meshes (--weights)"),
    Command("mean", ("blend",), "the form-space mean of meshes with the same faces",
            groups=("solve",)),
    Command("transfer", ("transfer",),
            "apply the deformation SOURCE -> DEFORMED to TARGET (same faces)", nargs=3,
            groups=("solve",), inputs_help="SOURCE DEFORMED TARGET"),
    Command("convert", ("mesh",), "read, check and write meshes (formats from the "
            "extensions)"),
)}
"""Every ``ffs`` subcommand that runs operations (``serve`` aside), in the help's order."""
