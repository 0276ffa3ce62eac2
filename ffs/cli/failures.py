"""How a failed file is told: one line naming the file, the field and the index, as the
service's problem documents do, and no traceback for bad input."""

from __future__ import annotations

import re
from typing import Any

from ffs.cli.items import UsageError


class RunFailedError(Exception):
    """A file's run failed for a reason that is not an input error of the library (e.g.
    ``check --require-integrable``)."""


class StoppedError(Exception):
    """The batch was stopped (Ctrl-C or ``--fail-fast``) while this file ran."""


_NUMPY_SCALAR = re.compile(r"\bnp\.(?:float|int|uint|bool_?)\d*\(([^()]*)\)")


def _library_errors() -> tuple[Any, Any]:
    """The library's input errors: ``(SolverInputError, MeshFileError)``, or two empty
    tuples (which ``isinstance`` matches with nothing) where only the client is installed."""
    try:
        from solver.core.errors import SolverInputError
        from solver.mesh.io import MeshFileError
    except ImportError:  # pragma: no cover - the client without the library
        return (), ()
    return SolverInputError, MeshFileError


def describe_error(exc: BaseException) -> str:
    """One line for a failed file.

    Args:
        exc: What the run raised.

    Returns:
        The problem's detail and where it points (``field[index]: ...``), with numpy scalar
        reprs as plain numbers; an unexpected error is named as such, with a hint to ``-v``.
    """
    from ffs.files import InputFileError

    if isinstance(exc, InputFileError | RunFailedError | UsageError):
        return str(exc)
    solver_input_error, mesh_file_error = _library_errors()
    if isinstance(exc, solver_input_error):  # numpy scalar reprs as numbers, as the service
        return _NUMPY_SCALAR.sub(r"\1", f"{exc} ({exc.kind})")
    if isinstance(exc, mesh_file_error):
        return exc.reason
    from ffs.errors import FFSError, ProblemError

    if isinstance(exc, ProblemError):
        where = ""
        first = exc.errors[0] if exc.errors else {}
        if first.get("field") and not exc.detail.startswith(str(first["field"])):
            index = first.get("index")
            where = f"{first['field']}" + (f"[{index}]" if index is not None else "") + ": "
        hint = " (give the service's API key with --token or FFS_TOKEN)" \
            if exc.status == 401 else ""
        return f"{where}{exc.detail} ({exc.kind}){hint}"
    if isinstance(exc, FFSError):
        return str(exc)
    if isinstance(exc, MemoryError):
        return "out of memory"
    if isinstance(exc, OSError):
        return f"{exc.filename or ''}: {exc.strerror or exc}".lstrip(": ")
    return f"unexpected error ({type(exc).__name__}: {exc}); run with -v for the traceback"


def is_expected(exc: BaseException) -> bool:
    """Whether ``exc`` is a failure the command explains (``-v`` adds no traceback)."""
    from ffs.errors import FFSError
    from ffs.files import InputFileError

    expected = (InputFileError, RunFailedError, FFSError, OSError, MemoryError,
                *_library_errors())
    return isinstance(exc, expected)
