"""``ffs``: the command line (``ffs <command> ...``, :mod:`ffs.cli`) and the Python client
(:class:`ffs.Client`, :mod:`ffs.client`) of the fundamental-forms service.

The client needs only ``httpx`` and ``numpy``; importing this package never imports FastAPI
or the service. The command line runs the work in-process through :mod:`solver`, or on a
service with ``--server URL`` (or ``FFS_SERVER``) through the client.
"""

from __future__ import annotations

from importlib import metadata
from typing import Any

try:
    __version__ = metadata.version("fundamental-forms-service")
except metadata.PackageNotFoundError:  # a source tree that was not installed
    __version__ = "0+unknown"

_EXPORTS = {
    "Client": "ffs.client", "Job": "ffs.jobs", "JobProgress": "ffs.jobs",
    "Session": "ffs.client",
    "Blend": "ffs.results", "Forms": "ffs.results", "Integrability": "ffs.results",
    "Mesh": "ffs.results", "Parameterization": "ffs.results",
}
"""Public names -> their module, imported on first use (``import ffs.cli`` must not load
numpy before the command line has set the BLAS thread variables)."""
_EXPORTS.update({name: "ffs.errors" for name in (
    "BadRequestError", "ServiceUnreachableError", "FFSError", "GoneError", "InvalidInputError",
    "JobCancelledError", "LocalFileError", "NotFoundError", "ProblemError",
    "RequestTimeoutError", "ServerError", "ServiceUnavailableError", "TooManyRequestsError")})
_EXPORTS.update({name: "ffs.errors" for name in ("UnauthorizedError", "ForbiddenError")})


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'ffs' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)


__all__ = [
    "BadRequestError",
    "Blend",
    "Client",
    "FFSError",
    "ForbiddenError",
    "Forms",
    "GoneError",
    "Integrability",
    "InvalidInputError",
    "Job",
    "JobCancelledError",
    "JobProgress",
    "LocalFileError",
    "Mesh",
    "NotFoundError",
    "Parameterization",
    "ProblemError",
    "RequestTimeoutError",
    "ServerError",
    "ServiceUnavailableError",
    "ServiceUnreachableError",
    "Session",
    "TooManyRequestsError",
    "UnauthorizedError",
    "__version__",
]
