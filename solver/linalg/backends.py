"""The native solvers behind :func:`solver.linalg.factorize` and the choice among them.

Each backend is a class whose constructor factorizes a canonical float64 CSR matrix and
whose ``solve`` back-substitutes (N, k) right-hand sides (:class:`NativeSolver`):
PARDISO (:class:`solver.linalg.pardiso.PardisoSolver`), CHOLMOD through cholespy and
SciPy's SuperLU. :func:`resolve_backend` maps a name (or ``"auto"``) to one that works here,
after a smoke test of its library.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp

from .errors import BackendUnavailableError, SingularSystemError
from .pardiso import PardisoSolver

BACKENDS: tuple[str, ...] = ("pardiso", "superlu", "cholespy")
"""Every backend name :func:`solver.linalg.factorize` knows, fastest first (see
``bench/LINALG.md``)."""

_PIP_PACKAGE: dict[str, str] = {"pardiso": "pypardiso", "cholespy": "cholespy", "superlu": "scipy"}


class NativeSolver(Protocol):
    """What each backend provides: a factor of the matrix and a solve with it."""

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve for ``rhs`` of shape (N, k) float64; return (N, k) float64."""
        ...


class CholespySolver:
    """CHOLMOD ``L L^T`` factor via cholespy, from the lower triangle.

    Args:
        matrix: (N, N) canonical float64 CSR, symmetric.

    Raises:
        ImportError: cholespy is not installed.
        SingularSystemError: CHOLMOD found the matrix not positive definite.
    """

    def __init__(self, matrix: sp.csr_array) -> None:
        import cholespy  # optional: imported lazily

        # Pass CSR: cholespy copies CSR/COO input, whereas it sorts CSC input in place and
        # reallocates it (unsafe on NumPy-owned memory). CHOLMOD reads the lower triangle.
        lower = sp.tril(matrix, format="csr")
        try:
            self._solver = cholespy.CholeskySolverD(
                int(matrix.shape[0]), lower.indptr.astype(np.int32, copy=False),
                lower.indices.astype(np.int32, copy=False),
                np.ascontiguousarray(lower.data, dtype=np.float64), cholespy.MatrixType.CSR)
        except ValueError as exc:
            if "positive definite" in str(exc):
                raise SingularSystemError(f"CHOLMOD factorization failed: {exc}") from exc
            raise

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Forward/back substitution; ``rhs`` (N, k) float64 -> (N, k) float64."""
        b = np.ascontiguousarray(rhs, dtype=np.float64)
        x = np.zeros_like(b)
        self._solver.solve(b, x)
        return x


_SUPERLU_OPTIONS: dict[str, Any] = {
    "permc_spec": "MMD_AT_PLUS_A",  # minimum degree on K + K^T: a symmetric ordering
    "diag_pivot_thresh": 0.0,  # always pivot on the diagonal (stable for SPD)
    "options": {"SymmetricMode": True},
}


class SuperluSolver:
    """SciPy SuperLU factor of the full (symmetric) matrix.

    Args:
        matrix: (N, N) canonical float64 CSR, symmetric.

    Raises:
        SingularSystemError: SuperLU found the matrix exactly singular.
    """

    def __init__(self, matrix: sp.csr_array) -> None:
        from scipy.sparse.linalg import splu  # lazy: keeps module import light

        # The CSR arrays of a symmetric matrix are also its CSC arrays: no copy.
        csc = sp.csc_array((matrix.data, matrix.indices, matrix.indptr), shape=matrix.shape)
        try:
            self._lu = splu(csc, **_SUPERLU_OPTIONS)
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise SingularSystemError(f"SuperLU factorization failed: {exc}") from exc

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Forward/back substitution; ``rhs`` (N, k) float64 -> (N, k) float64."""
        return np.asarray(self._lu.solve(np.asfortranarray(rhs, dtype=np.float64)))


class EmptySolver:
    """The 0 x 0 matrix (no native library accepts it)."""

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Return a copy of the (0, k) ``rhs``."""
        return np.array(rhs, dtype=np.float64)


SOLVERS: dict[str, Callable[[sp.csr_array], NativeSolver]] = {
    "pardiso": PardisoSolver,
    "cholespy": CholespySolver,
    "superlu": SuperluSolver,
}
"""Backend name -> the class that factorizes a canonical float64 CSR matrix with it."""


@functools.cache
def _unavailable_reason(backend: str) -> str | None:
    """``None`` if ``backend`` loads and solves a 2 x 2 system here, else why not."""
    if backend == "superlu":
        return None
    try:
        solver = SOLVERS[backend](sp.csr_array(np.array([[4.0, 1.0], [1.0, 3.0]])))
        x = solver.solve(np.array([[5.0], [4.0]]))
    except ImportError as exc:  # in words: "No module named 'cholespy'", no exception name
        return str(exc) or f"{_PIP_PACKAGE.get(backend, backend)} does not import"
    except Exception as exc:  # any failure means "do not use it"
        return f"its test solve of a 2 x 2 system failed ({exc})"
    if not np.allclose(x.ravel(), [1.0, 1.0], rtol=1e-12, atol=0.0):
        return f"smoke test returned a wrong solution {x.ravel().tolist()}"
    return None


def available_backends() -> list[str]:
    """Backends usable in this process, fastest first.

    The first call loads each optional library and solves a 2 x 2 system with it
    (about 30 ms in all); the results are cached for the life of the process.

    Returns:
        Names from :data:`BACKENDS`; always includes ``"superlu"``.

    Example:
        >>> from solver.linalg import available_backends
        >>> "superlu" in available_backends()
        True
    """
    return [name for name in BACKENDS if _unavailable_reason(name) is None]


def default_backend() -> str:
    """The fastest available backend (what ``backend="auto"`` selects)."""
    return available_backends()[0]


def resolve_backend(backend: str) -> str:
    """Map ``"auto"`` to the default backend and validate a backend name.

    Call it before any work on paths that may not factorize at all (e.g. tree
    integration), so an invalid choice is refused on every path.

    Args:
        backend: ``"auto"`` or one of :data:`BACKENDS`.

    Returns:
        An available backend name.

    Raises:
        ValueError: an unknown name.
        BackendUnavailableError: a known backend that cannot be loaded here (the message
            names the pip package).

    Example:
        >>> from solver.linalg import resolve_backend
        >>> resolve_backend("superlu")
        'superlu'
        >>> resolve_backend("umfpack")
        Traceback (most recent call last):
        ...
        ValueError: unknown linear-algebra backend 'umfpack'; valid names: 'auto', ...
    """
    if backend == "auto":
        return default_backend()
    if backend not in BACKENDS:
        valid = ", ".join(repr(name) for name in ("auto", *BACKENDS))
        raise ValueError(f"unknown linear-algebra backend {backend!r}; valid names: {valid}")
    reason = _unavailable_reason(backend)
    if reason is not None:
        raise BackendUnavailableError(
            f"backend {backend!r} is not available here ({reason}); install it with "
            f"`pip install {_PIP_PACKAGE[backend]}` or use one of {available_backends()}")
    return backend
