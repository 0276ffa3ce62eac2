"""The two errors of the factorization layer (re-exported by :mod:`solver.linalg`)."""

from __future__ import annotations

from ..core.errors import SolverInputError


class BackendUnavailableError(SolverInputError, ImportError):
    """A known backend whose library cannot be loaded in this environment.

    It is both a :class:`~solver.core.errors.SolverInputError` (a bad ``backend`` argument, the
    ``solver`` option) and an :class:`ImportError` (a missing optional dependency); the
    message names the pip package to install.
    """

    kind = "invalid-option"

    def __init__(self, reason: str) -> None:
        super().__init__(reason, field="options.solver", message=reason)


class SingularSystemError(SolverInputError, RuntimeError):
    """The matrix is singular or not positive definite.

    Raised when the factorization fails, or when a solve produces a non-finite or
    inaccurate result. A :class:`~solver.core.errors.SolverInputError` naming ``constraints``:
    the constraints given (or their absence) leave the system singular.
    """

    kind = "singular-system"

    def __init__(self, reason: str) -> None:
        super().__init__(reason, field="constraints",
                         message=f"the linear system is singular: {reason}")
