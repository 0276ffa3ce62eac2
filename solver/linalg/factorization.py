"""The factorization layer: validate a sparse SPD matrix, factorize it once, solve many times.

:func:`factorize` checks and copies the matrix, picks the backend
(:func:`solver.linalg.backends.resolve_backend`) and returns a :class:`Factorization`, whose
:meth:`~Factorization.solve` back-substitutes and checks the residual of its first answer.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import scipy.sparse as sp

from .backends import SOLVERS, EmptySolver, NativeSolver, resolve_backend
from .errors import SingularSystemError
from .pardiso import PardisoSolver, analyze_upper

RESIDUAL_TOLERANCE: float = 1e-6
"""Largest accepted relative residual ``||K x - b|| / ||b||`` of a solved column."""

REFINEMENT_STEPS: int = 3
"""Iterative-refinement steps a solve tries before it refuses an inaccurate answer."""

_INT32_MAX = np.iinfo(np.int32).max


def _is_real(dtype: np.dtype) -> bool:
    """Whether ``dtype`` is a real number type (bool, integer or floating point)."""
    return bool(np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)
                or np.issubdtype(dtype, np.bool_))


def _canonical_matrix(matrix: Any, assume_symmetric: bool = False) -> sp.csr_array:
    """Validate ``matrix`` and return an owned, canonical float64 CSR copy.

    Args:
        matrix: (N, N) real scipy.sparse matrix or array.
        assume_symmetric: skip the symmetry check.

    Returns:
        (N, N) float64 CSR, sorted int32 indices, no duplicates.

    Raises:
        TypeError: a non-sparse or complex matrix.
        ValueError: a non-square, too large (beyond 32-bit indices) or non-symmetric one.
        SingularSystemError: non-finite (NaN or infinite) entries.
    """
    if not sp.issparse(matrix):
        raise TypeError("matrix must be a scipy.sparse matrix or array, "
                        f"not {type(matrix).__name__}")
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise ValueError(f"matrix must be square, got shape {matrix.shape}")
    if not _is_real(matrix.dtype):
        raise TypeError(f"matrix must be real, got dtype {matrix.dtype}")
    K = sp.csr_array(matrix, dtype=np.float64, copy=True)
    K.sum_duplicates()  # also sorts the column indices of every row
    if max(K.shape[0], K.nnz) > _INT32_MAX:
        raise ValueError("matrix too large for 32-bit sparse indices: "
                         f"shape {K.shape}, nnz {K.nnz}")
    K.indptr = K.indptr.astype(np.int32, copy=False)
    K.indices = K.indices.astype(np.int32, copy=False)
    if not np.isfinite(K.data).all():
        raise SingularSystemError("matrix has non-finite (NaN or infinite) entries: the "
                                  "input values overflow double precision")
    if K.nnz and not assume_symmetric:
        scale = float(np.abs(K.data).max())
        asymmetry = float(abs(K - K.T).max())
        if asymmetry > 1e-10 * scale:
            raise ValueError(f"matrix is not symmetric: max |K - K^T| = {asymmetry:.3g} "
                             f"(max |K| = {scale:.3g})")
    return K


class Factorization:
    """A factorized sparse SPD matrix ``K``; :meth:`solve` only back-substitutes.

    Create it with :func:`factorize` rather than directly. It keeps a private copy of ``K``
    (for the residual check and for pickling) besides the factor.

    Args:
        matrix: (N, N) canonical float64 CSR, symmetric; with ``upper``, only its upper
            triangle, every diagonal entry stored.
        backend: a validated, available backend name.
        groups: validated (N,) int64 ordering hint, or None.
        upper: ``matrix`` is the upper triangle only.
        precision: ``"double"``, or ``"single"``: PARDISO factorizes a float32 copy and
            solves in float32, and the residuals of its solves are not checked (relative
            residuals ~1e-7 x the condition number; the caller judges the answers). Other
            backends ignore it.

    Attributes:
        backend: the backend name that computed it.
        precision: the precision of the factor (``"double"`` for every backend but
            PARDISO).
        size: N, the order of ``K``.
        analysis: ``"cached"`` when the fill-reducing ordering of a factorization with the
            same sparsity pattern was reused from this process's analysis cache (PARDISO
            only), else ``"computed"``.
        timings: seconds: ``"analysis"``, the ordering and symbolic factorization (0 when a
            cached handle was reused), and ``"factorization"``, the numerical factorization;
            other backends report their whole factorization under ``"factorization"``.
    """

    backend: str
    size: int
    analysis: str
    timings: dict[str, float]

    def __init__(self, matrix: sp.csr_array, backend: str,
                 groups: np.ndarray | None = None, upper: bool = False,
                 precision: str = "double") -> None:
        self.backend = backend
        single = precision == "single" and backend == "pardiso" and matrix.shape[0] > 0
        self.precision = "single" if single else "double"
        self.size = int(matrix.shape[0])
        self._upper = upper and backend == "pardiso"  # PARDISO reads the triangle as is
        if upper and not self._upper:
            matrix = _symmetric_from_upper(matrix)
        self._matrix = matrix
        self._groups = groups
        self._lock = threading.Lock()
        self._verified = False  # set by the first solve whose residual is checked
        start = time.perf_counter()
        if self.size == 0:
            self._solver: NativeSolver = EmptySolver()
        elif backend == "pardiso":
            self._solver = PardisoSolver(matrix, groups, self._upper,
                                         single=self.precision == "single")
        else:
            self._solver = SOLVERS[backend](matrix)
        self.analysis = getattr(self._solver, "analysis", "computed")
        self.timings = getattr(self._solver, "timings",
                               {"analysis": 0.0, "factorization": time.perf_counter() - start})

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve ``K x = rhs``.

        The residual is checked (and improved by iterative refinement if needed) until one
        solve has passed; after that the factor is trusted and only finiteness is checked,
        so repeated solves cost one back-substitution each. A single-precision factor's
        residuals are never checked (only finiteness: its callers refine its answers).

        Args:
            rhs: real array of shape (N,) or (N, k) (converted to float64).

        Returns:
            ``x``, float64, the shape of ``rhs``.

        Raises:
            SingularSystemError: some column of ``x`` is non-finite or has a relative
                residual ``||K x - b|| / ||b||`` above :data:`RESIDUAL_TOLERANCE` (for
                ``b = 0``: any nonzero residual).
            ValueError: a wrong shape or non-finite ``rhs``.
            TypeError: a complex ``rhs``.
        """
        b = np.asarray(rhs)
        if b.ndim not in (1, 2) or b.shape[0] != self.size:
            raise ValueError(
                f"rhs must have shape ({self.size},) or ({self.size}, k), got {b.shape}")
        if not _is_real(b.dtype):
            raise TypeError(f"rhs must be real, got dtype {b.dtype}")
        b2 = b.astype(np.float64, copy=False)
        if b2.ndim == 1:
            b2 = b2[:, None]
        if not np.isfinite(b2).all():
            raise ValueError("rhs has non-finite (NaN or infinite) entries")
        if b2.shape[1] == 0:
            return np.zeros(b.shape, dtype=np.float64)
        with self._lock:
            x = self._solver.solve(b2)
            if (self._verified or self.precision == "single") and np.isfinite(x).all():
                # The factor passed the residual check once: a backward-stable solve with
                # the same factor needs no second opinion (this keeps drags cheap). A
                # single-precision factor is never checked: its callers accept inexact
                # answers (e.g. Gauss-Newton steps, which a line search judges).
                return np.ascontiguousarray(x.reshape(b.shape))
            residual = self._relative_residual(x, b2)
            # Iterative refinement, only when the first answer is not accurate enough
            # (ill-conditioned but nonsingular systems): x += K^-1 (b - K x).
            for _ in range(REFINEMENT_STEPS):
                if residual <= RESIDUAL_TOLERANCE:
                    break
                x = x + self._solver.solve(b2 - self._product(x))
                residual = self._relative_residual(x, b2)
        self._raise_if_inaccurate(x, residual)
        self._verified = True
        return np.ascontiguousarray(x.reshape(b.shape))

    def _product(self, x: np.ndarray) -> np.ndarray:
        """K @ x (N, k), also where only K's upper triangle is kept."""
        K = self._matrix
        return upper_symmetric_product(K, x) if self._upper else K @ x

    def _relative_residual(self, x: np.ndarray, b: np.ndarray) -> float:
        """max over columns of ||K x - b|| / ||b|| (inf for a nonzero residual of b = 0)."""
        if not np.isfinite(x).all():
            return float("inf")
        residual = np.linalg.norm(self._product(x) - b, axis=0)
        norm_b = np.linalg.norm(b, axis=0)
        relative = np.where(norm_b > 0, residual / np.where(norm_b > 0, norm_b, 1.0),
                            np.where(residual > 0, np.inf, 0.0))
        return float(relative.max())

    def _raise_if_inaccurate(self, x: np.ndarray, residual: float) -> None:
        """Raise :class:`SingularSystemError` unless ``x`` is finite and its relative
        residual is within :data:`RESIDUAL_TOLERANCE`."""
        if not np.isfinite(x).all():
            raise SingularSystemError(
                f"{self.backend}: the solution is not finite; the matrix is singular or not "
                "positive definite")
        if not residual <= RESIDUAL_TOLERANCE:  # also catches NaN
            raise SingularSystemError(
                f"{self.backend}: relative residual ||Kx - b|| / ||b|| = {residual:.3g} "
                f"exceeds {RESIDUAL_TOLERANCE:g}; the matrix is singular, not positive "
                "definite or too ill-conditioned")

    def __repr__(self) -> str:
        return (f"Factorization(backend={self.backend!r}, size={self.size}, "
                f"nnz={self._matrix.nnz}, analysis={self.analysis!r})")

    def __getstate__(self) -> dict[str, Any]:
        """Pickle the backend name and the matrix, never the native factor."""
        K = self._matrix
        return {"backend": self.backend, "shape": K.shape,
                "indptr": K.indptr, "indices": K.indices, "data": K.data,
                "groups": self._groups, "upper": self._upper, "precision": self.precision}

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Unpickle by factorizing the matrix again with the same backend."""
        matrix = sp.csr_array((state["data"], state["indices"], state["indptr"]),
                              shape=state["shape"])
        backend = resolve_backend(state["backend"])
        upper = state.get("upper", False)
        if upper and backend != "pardiso":
            matrix, upper = _symmetric_from_upper(matrix), False
        self.__init__(matrix, backend, state.get("groups"), upper,  # type: ignore[misc]
                      state.get("precision", "double"))


def upper_symmetric_product(upper: sp.csr_array, x: np.ndarray) -> np.ndarray:
    """``K @ x`` for the symmetric ``K`` of which ``upper`` is the upper triangle.

    Args:
        upper: (N, N) CSR upper triangle of ``K``, diagonal included.
        x: (N,) or (N, k) float64.

    Returns:
        ``U x + U^T x - diag(U) x``, the shape of ``x``.
    """
    diagonal = upper.diagonal()
    return upper @ x + upper.T @ x - (diagonal if x.ndim == 1 else diagonal[:, None]) * x


def _symmetric_from_upper(U: sp.csr_array) -> sp.csr_array:
    """The symmetric matrix (canonical CSR, int32 indices) whose upper triangle is ``U``."""
    K = sp.csr_array(U + U.T - sp.diags_array(U.diagonal()))
    K.sum_duplicates()
    K.indptr = K.indptr.astype(np.int32, copy=False)
    K.indices = K.indices.astype(np.int32, copy=False)
    return K


def factorize(matrix: sp.spmatrix | sp.sparray, backend: str = "auto",
              assume_symmetric: bool = False, groups: Any = None,
              triangle: str = "full", precision: str = "double") -> Factorization:
    """Factorize a sparse symmetric positive definite matrix for repeated solves.

    Args:
        matrix: (N, N) real, any scipy.sparse format (matrix or array); it is copied (as
            float64 CSR), so later changes to it do not affect the factorization. It must
            be symmetric to 1e-10 relative to its largest entry (each backend reads the
            triangle it needs).
        backend: one of :data:`solver.linalg.BACKENDS` or ``"auto"``
            (:func:`solver.linalg.default_backend`).
        assume_symmetric: skip the symmetry check (for matrices symmetric by construction,
            such as ``A^T W A``).
        groups: optional (N,) int ordering hint, the group of each unknown, where the
            unknowns of a group couple with the same others (a vertex's or a face frame's
            coordinates): PARDISO then computes its fill-reducing ordering on the
            compressed graph (one node per group; about half the analysis time on the
            reconstruction system, and no more fill) instead of the whole pattern. Only the
            ordering depends on it, never the solution; other backends ignore it. The
            price: PARDISO given an ordering makes a classic factor instead of its
            two-level one, whose solves are 1.3-1.5x faster (``bench/drag_regression.py``);
            so give ``groups`` for a factorization solved once or a few times, not for one
            solved per frame (the ``Deformer``).
        triangle: ``"full"``, or ``"upper"``: ``matrix`` holds only the upper triangle of
            the symmetric matrix, every diagonal entry stored (explicit zeros included), as
            a canonical CSR array (sorted, no duplicates) -- e.g. a Gauss-Newton matrix
            assembled straight into that pattern. PARDISO then reads it without a copy;
            other backends symmetrize it.
        precision: ``"double"``, or ``"single"``: PARDISO factorizes and solves in float32
            (about half the factorization time on the refinement's Gauss-Newton matrix:
            ``python -m bench.gauss_newton_factor``), solutions returned as float64 and not
            residual-checked; for callers that accept inexact solves of well-conditioned
            matrices. Other backends ignore it.

    Returns:
        The :class:`Factorization`.

    Raises:
        ValueError: an unknown backend name or precision; a non-square or non-symmetric
            matrix; ``groups`` not N integers in [0, N); a ``triangle="upper"`` matrix with
            entries below the diagonal or a diagonal entry missing.
        TypeError: not a real sparse matrix.
        BackendUnavailableError: a known backend that is not installed.
        SingularSystemError: non-finite entries, or the backend found the matrix singular
            or not positive definite (others are only detected by
            :meth:`Factorization.solve`).

    Example:
        >>> import numpy as np
        >>> import scipy.sparse as sp
        >>> from solver.linalg import factorize
        >>> fact = factorize(sp.csr_array([[4.0, 1.0], [1.0, 3.0]]), backend="superlu")
        >>> fact.solve(np.array([5.0, 4.0])).round(12).tolist()
        [1.0, 1.0]
        >>> fact.solve(np.eye(2)).shape
        (2, 2)
    """
    name = resolve_backend(backend)
    if precision not in ("double", "single"):
        raise ValueError(f"precision must be 'double' or 'single', got {precision!r}")
    if triangle == "upper":
        return Factorization(_upper_csr(matrix), name,
                             _ordering_groups(groups, matrix.shape[0]), upper=True,
                             precision=precision)
    if triangle != "full":
        raise ValueError(f"triangle must be 'full' or 'upper', got {triangle!r}")
    K = _canonical_matrix(matrix, assume_symmetric)
    return Factorization(K, name, _ordering_groups(groups, K.shape[0]), precision=precision)


def analyze(matrix: sp.spmatrix | sp.sparray, backend: str = "auto",
            precision: str = "double") -> bool:
    """Prepare the first :func:`factorize` of a pattern ahead of time: with PARDISO, compute
    and cache its analysis (ordering and symbolic factorization), which only the sparsity
    pattern determines, so that the factorization later pays only its numerical phase.
    Other backends keep no analysis: nothing is done.

    Args:
        matrix: (N, N) upper triangle as :func:`factorize` reads it with
            ``triangle="upper"`` (canonical CSR, every diagonal entry stored); its values
            are not read.
        backend: as in :func:`factorize`.
        precision: as in :func:`factorize` (single and double precision keep separate
            analyses).

    Returns:
        Whether an analysis was computed (False: another backend, or PARDISO had it
        cached already, or the cache is disabled).

    Example:
        >>> import scipy.sparse as sp
        >>> from solver.linalg import analyze, factorize
        >>> upper = sp.csr_array([[4.0, 1.0], [0.0, 3.0]])
        >>> first = analyze(upper)
        >>> factorize(upper, triangle="upper").solve([5.0, 4.0]).round(12).tolist()
        [1.0, 1.0]
    """
    if resolve_backend(backend) != "pardiso":
        return False
    return analyze_upper(_upper_csr(matrix), single=precision == "single")


def _upper_csr(matrix: Any) -> sp.csr_array:
    """Validate the upper triangle given to ``factorize(..., triangle="upper")``.

    Args:
        matrix: (N, N) upper-triangular scipy.sparse matrix, every diagonal entry stored.

    Returns:
        Canonical float64 CSR (int32 indices), uncopied when it already is one.

    Raises:
        TypeError, ValueError, SingularSystemError: as :func:`_canonical_matrix`, and
            ValueError for an entry below the diagonal or a missing diagonal entry.
    """
    if not (isinstance(matrix, sp.csr_array) and matrix.dtype == np.float64
            and matrix.has_canonical_format):
        matrix = _canonical_matrix(matrix, assume_symmetric=True)
    n = matrix.shape[0]
    if matrix.ndim != 2 or matrix.shape[1] != n:
        raise ValueError(f"matrix must be square, got shape {matrix.shape}")
    indptr = matrix.indptr.astype(np.int32, copy=False)
    indices = matrix.indices.astype(np.int32, copy=False)
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(indptr))
    if (indices < rows).any():
        raise ValueError("triangle='upper' but the matrix has entries below the diagonal")
    if np.count_nonzero(indices == rows) != n:
        raise ValueError("triangle='upper' needs every diagonal entry stored")
    if not np.isfinite(matrix.data).all():
        raise SingularSystemError("matrix has non-finite (NaN or infinite) entries: the "
                                  "input values overflow double precision")
    return sp.csr_array((matrix.data, indices, indptr), shape=matrix.shape)


def _ordering_groups(groups: Any, n: int) -> np.ndarray | None:
    """Validate the ``groups`` hint of :func:`factorize`.

    Args:
        groups: (n,) integers in [0, n), or None.
        n: order of the matrix.

    Returns:
        (n,) int64, or None (no hint, or an empty matrix).

    Raises:
        ValueError: not n integers in [0, n).
    """
    if groups is None:
        return None
    g = np.asarray(groups)
    if g.shape != (n,) or (n and g.dtype.kind not in "iu"):
        raise ValueError(f"groups must be {n} integers (one per unknown), got shape "
                         f"{g.shape} and dtype {g.dtype}")
    g = g.astype(np.int64)
    if n and (g.min() < 0 or g.max() >= n):
        raise ValueError(f"groups must lie in [0, {n}), got [{g.min()}, {g.max()}]")
    return g if n else None
