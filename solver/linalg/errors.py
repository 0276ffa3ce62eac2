"""The two errors of the factorization layer (re-exported by :mod:`solver.linalg`)."""

from __future__ import annotations


class BackendUnavailableError(ValueError, ImportError):
    """A known backend whose library cannot be loaded in this environment.

    It is both a :class:`ValueError` (a bad ``backend`` argument) and an
    :class:`ImportError` (a missing optional dependency); the message names the pip
    package to install.
    """


class SingularSystemError(RuntimeError):
    """The matrix is singular or not positive definite.

    Raised when the factorization fails, or when a solve produces a non-finite or
    inaccurate result.
    """
