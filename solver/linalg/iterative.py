"""Iterative solves of a sparse SPD matrix for large meshes: preconditioned conjugate gradients
with a smoothed-aggregation multigrid preconditioner (pyamg), no factorization.

Eq. 5's matrix at 1.6M faces (5.6M unknowns, 78M nonzeros) does not fit a Cholesky factor in
10 GiB; its multigrid hierarchy is a small multiple of the matrix itself. Smoothed aggregation
needs the matrix's near-null space: for Eq. 5 (per coordinate) the translation (1 on the
positions, 0 on the frames) and the three columns of any immersion of the forms (the tree
integration), which span the energy's kernel for exact forms and its lowest modes for noisy
ones. Measured on the 100K-face scan with noise (``bench/README.md``, "Iterative linear path"):
19 iterations to a relative residual of 1e-7 with these four candidates against 500 and no
convergence with the constant alone.

:class:`LinearSolverRules` decides direct against iterative (one home for the face threshold
and the memory models, which the service's admission reads); :class:`IterativeSolver` sets up
the hierarchy once (:func:`solver.linalg.hierarchy.smoothed_aggregation`) and solves several
right-hand sides, one CG after the other (one W-cycle per iteration). The hierarchy and
its cycles are single precision (``LinearSolverRules.preconditioner_dtype``); CG, its
residuals and the answer are float64.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import scipy.sparse as sp

from .blocked import ROWS_PER_UPDATE, axpy
from .cost import PowerLaw
from .errors import BackendUnavailableError
from .hierarchy import smoothed_aggregation

LinearSolver = Literal["auto", "direct", "iterative"]
LINEAR_SOLVERS: tuple[str, ...] = ("auto", "direct", "iterative")
"""The values of the ``linear_solver`` option."""


DIRECT_MEMORY = PowerLaw(per_face=8_300.0)
"""Peak bytes of Eq. 5's linear answer by a factorization (``bench.scale``, noisy forms,
``refine=False``: 803-883 MB at 100K faces, 3.0-3.3 GB at 400K)."""
ITERATIVE_MEMORY = PowerLaw(per_face=2_600.0, base=150e6)
"""Peak bytes of the linear answer by multigrid-preconditioned CG (the normal matrix's
assembly, the multigrid setup's or CG's; ``bench.scale``: 345 MiB at 100K faces, 1006 MiB at
400K, 3753 MiB at 1.6M since the hierarchy is set up level by level (was 434, 1280 and 4899);
2.4 KB per face beyond 150 MB; the model is 9-13 % above)."""


@dataclass(frozen=True)
class LinearSolverRules:
    """Direct (factorization) or iterative (multigrid-preconditioned CG), and the memory each
    takes: the one home of that choice.

    Attributes:
        face_threshold: ``auto`` solves meshes of at least this many faces iteratively;
            below it, only where the direct path's memory estimate exceeds the memory
            available (a factorization is faster wherever it fits: measured in
            ``bench/README.md``, "Iterative linear path").
        direct_memory, iterative_memory: peak bytes of a solve (the process included) by
            each path as a function of the face count (:class:`~solver.linalg.cost.PowerLaw`,
            fitted to ``bench.scale``); ``auto`` goes iterative where ``direct_memory``
            exceeds the memory given. The service's admission prices a request by the same
            models (``service.backends.admission``).
        relative_tolerance: CG stops at ``||K x - b|| <= tol * ||b||`` per column.
        start_tolerance: the same where the answer only starts the refinement (noisy forms,
            ``refine`` not false: the layout fit of the linear answer is its start, and the
            refinement's optimum does not depend on it; ``bench/README.md``, "Iterative
            refinement"). A linear answer that turns out to be returned after all is solved
            on to ``relative_tolerance`` from there.
        preconditioner_dtype: the multigrid hierarchy's and cycle's precision (CG, its
            residuals and the answer stay float64): float32 halves the cycle's memory traffic
            and the hierarchy's memory for the same iteration counts (``bench/README.md``).
        max_iterations: CG gives up after this many iterations (reported, not raised).
    """

    face_threshold: int = 2_000_000
    direct_memory: PowerLaw = DIRECT_MEMORY
    iterative_memory: PowerLaw = ITERATIVE_MEMORY
    relative_tolerance: float = 1e-8
    start_tolerance: float = 1e-3
    max_iterations: int = 300
    preconditioner_dtype: str = "float32"

    def choose(self, n_faces: int, requested: str | None = "auto",
               memory_bytes: float | None = None) -> str:
        """``"direct"`` or ``"iterative"`` for a mesh of ``n_faces`` faces.

        Args:
            n_faces: the mesh's face count.
            requested: the ``linear_solver`` option (None or ``"auto"``: by size and memory).
            memory_bytes: the memory the solve may use (None: not considered).

        Example:
            >>> rules = LinearSolverRules(face_threshold=1000)
            >>> rules.choose(999), rules.choose(1000), rules.choose(10, "iterative")
            ('direct', 'iterative', 'iterative')
        """
        if requested not in (None, "auto"):
            if requested not in LINEAR_SOLVERS:
                raise ValueError(f"unknown linear solver {requested!r}; expected one of "
                                 f"{LINEAR_SOLVERS}")
            return requested
        if n_faces >= self.face_threshold:
            return "iterative"
        if memory_bytes is not None and self.direct_memory.at(n_faces) > memory_bytes:
            return "iterative"
        return "direct"


RULES = LinearSolverRules()
"""The rules in force."""


def available_memory(budget: float | None = None) -> float | None:
    """Bytes this process may use for a solve: ``budget`` when given (the service's
    FFS_MAX_REQUEST_MEMORY: the machine's memory is shared among its workers by that budget,
    so a worker chooses by it, as its admission priced the request, and not by what the
    machine has free at that moment), else the machine's available memory (``/proc/meminfo``
    MemAvailable); either capped by the address-space limit (``RLIMIT_AS``) less what the
    process already maps. None where none of them is known.

    Example:
        >>> available_memory(1e6) <= 1e6
        True
    """
    limits = [float(budget) if budget is not None else _mem_available(),
              _address_space_room()]
    known = [limit for limit in limits if limit is not None]
    return min(known) if known else None


def _mem_available() -> float | None:
    """The machine's available memory (``/proc/meminfo`` MemAvailable), bytes."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024.0
    except OSError:
        pass
    return None


def _address_space_room() -> float | None:
    """The address-space limit (``RLIMIT_AS``) less what this process maps, bytes; None
    without a limit."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/statm") as fh:
            mapped = int(fh.read().split()[0]) * resource.getpagesize()
        return float(soft - mapped)
    except (OSError, ImportError, ValueError):
        return None


def _multigrid() -> Any:
    try:
        import pyamg
    except ImportError as error:  # pragma: no cover - a declared dependency
        raise BackendUnavailableError("the iterative linear solver needs pyamg: "
                                      "pip install pyamg") from error
    return pyamg


@dataclass
class IterativeStats:
    """What an iterative solve did (the answer's report).

    Attributes:
        iterations: CG iterations (the largest over the right-hand sides).
        relative_residual: the largest ``||K x - b|| / ||b||`` over the columns.
        converged: every column reached the tolerance.
        setup_seconds, solve_seconds: multigrid setup and CG wall time.
        levels: levels of the multigrid hierarchy.
        operator_complexity: nonzeros of all levels over the fine matrix's.
        precision: the preconditioner's dtype name.
    """

    iterations: int = 0
    relative_residual: float = 0.0
    converged: bool = True
    setup_seconds: float = 0.0
    solve_seconds: float = 0.0
    levels: int = 0
    operator_complexity: float = 1.0
    tolerance: float = field(default=RULES.relative_tolerance)
    precision: str = "float64"

    def report(self) -> dict[str, Any]:
        """JSON-ready summary."""
        return {"method": "iterative", "iterations": int(self.iterations),
                "relative_residual": float(self.relative_residual),
                "tolerance": float(self.tolerance), "converged": bool(self.converged),
                "preconditioner": "smoothed aggregation", "levels": int(self.levels),
                "precision": self.precision,
                "operator_complexity": round(float(self.operator_complexity), 3),
                "setup_seconds": round(self.setup_seconds, 4),
                "solve_seconds": round(self.solve_seconds, 4)}


def digits_share(start: float, residual: float, target: float) -> float:
    """The share, 0 to 1, of the digits a CG solve must take off its residual (from
    ``start`` down to ``target``) that it has taken off at ``residual``:
    ``log(start / residual) / log(start / target)``; 1 where nothing was to be done.

    Example:
        >>> digits_share(1.0, 1e-3, 1e-6), digits_share(1.0, 2.0, 1e-6)
        (0.5, 0.0)
        >>> digits_share(1e-7, 1e-7, 1e-6)  # at the target from the start
        1.0
    """
    if not start > target > 0:
        return 1.0
    if not residual > 0:
        return 1.0
    share = math.log(start / residual) / math.log(start / target)
    return min(max(share, 0.0), 1.0)


class SolveProgress:
    """How far a CG solve of ``columns`` right-hand sides is, for ``progress(fraction)``.

    A column's fraction is the share of the digits its residual must lose that it has lost,
    ``log(start / residual) / log(start / target)`` (0 to 1; CG's residual falls about
    geometrically under a good preconditioner, so this is close to the share of its time);
    the solve's is ``(column + that) / columns``. ``progress`` is called only when the
    fraction has grown by :attr:`step` or more, or reached 1 (a solve of hundreds of
    iterations reports ~100 times), and never when it is None.

    Example:
        >>> seen = []
        >>> report = SolveProgress(seen.append, columns=2)
        >>> observe = report.column(1)
        >>> observe(1.0, 1e-2, 1e-4)    # half the digits of the second column
        >>> seen
        [0.75]
    """

    step = 0.01

    def __init__(self, progress: Callable[[float], None] | None, columns: int) -> None:
        self._progress = progress
        self._columns = max(int(columns), 1)
        self._reported = -1.0

    def column(self, index: int) -> Callable[[float, float, float], None]:
        """``observe(start, residual, target)`` for the column ``index`` (0-based)."""
        def observe(start: float, residual: float, target: float) -> None:
            if self._progress is None:
                return
            fraction = (index + digits_share(start, residual, target)) / self._columns
            if fraction >= self._reported + self.step or (fraction == 1.0 > self._reported):
                self._reported = fraction
                self._progress(float(fraction))
        return observe


class IterativeSolver:
    """Smoothed-aggregation multigrid of an SPD matrix; :meth:`solve` runs preconditioned CG.

    Args:
        matrix: (N, N) float64 sparse SPD matrix (CSR preferred; not copied when CSR).
        near_null: (N, k) float64 candidates of the near-null space (k small, e.g. 4), or
            None for the constant vector.
        rules: tolerance and iteration limit.

    Attributes:
        stats: :class:`IterativeStats` of the last solve (and of the setup).
    """

    def __init__(self, matrix: sp.spmatrix, near_null: np.ndarray | None = None,
                 rules: LinearSolverRules = RULES) -> None:
        _multigrid()  # pyamg is there (or a clear error)
        start = time.perf_counter()
        self.matrix = sp.csr_matrix(matrix)
        self.size = int(self.matrix.shape[0])
        self.rules = rules
        dtype = np.dtype(rules.preconditioner_dtype)
        B = None if near_null is None else np.ascontiguousarray(near_null, dtype=dtype)
        # Jacobi-smoothed prolongators weighted row by row ("local"): pyamg's default
        # estimates a spectral radius per level by Arnoldi, 12 of the 15 s of the setup on
        # the 100K-face scan; the candidates are not pre-smoothed (same iterations, -25%).
        # The hierarchy is built and cycled in rules.preconditioner_dtype (float32: the
        # cycle's memory traffic halved, the same iterations; CG itself stays float64).
        fine = self.matrix
        if dtype != fine.dtype:  # values converted; the index arrays are shared, not copied
            fine = sp.csr_matrix((fine.data.astype(dtype), fine.indices, fine.indptr),
                                 shape=fine.shape, copy=False)
        # The fine level's strength graph is the matrix itself: pyamg's symmetric strength
        # at theta 0 keeps every stored entry (the same pattern, so the same aggregates;
        # its values serve no one with unfiltered Jacobi smoothing), so no copy of it is
        # made (8 bytes per nonzero, ~10 % of the setup's peak at 100K faces).
        # Set up level by level in bounded memory (solver.linalg.hierarchy: pyamg's
        # hierarchy without its copies of the matrix and of R A).
        self._ml = smoothed_aggregation(
            fine, B=B, max_coarse=500, coarse_solver="splu",
            strength=[("predefined", {"C": fine}), "symmetric"],
            smooth=("jacobi", {"weighting": "local"}), improve_candidates=None,
            symmetry="symmetric")  # real symmetric: R = P^T, no conjugated copy
        del fine
        # W-cycles: 18 and 33 CG iterations on the 100K- and 400K-face noisy scans against
        # V-cycles' 24 and 58, for about the same CPU time at 100K and less at 400K.
        self._preconditioner = self._ml.aspreconditioner(cycle="W")
        for level in self._ml.levels:  # the candidates serve the setup only (cycles never
            level.B = None             # read them): 90 MB at 1.6M faces
        self._dtype = dtype
        self.stats = IterativeStats(setup_seconds=time.perf_counter() - start,
                                    levels=len(self._ml.levels),
                                    operator_complexity=self._ml.operator_complexity(),
                                    tolerance=rules.relative_tolerance,
                                    precision=dtype.name)

    def _precondition(self, r: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        """One cycle on ``r`` (N,) float64 from a zero guess, written into ``out`` (a new
        float64 array where ``out`` is None)."""
        cycle = self._preconditioner @ r.astype(self._dtype)
        if out is None:
            return np.asarray(cycle, dtype=np.float64)
        out[:] = cycle
        return out

    def solve(self, rhs: np.ndarray | Callable[[int], np.ndarray],
              guess: np.ndarray | None = None, tolerance: float | None = None,
              columns: int | None = None,
              progress: Callable[[float], None] | None = None) -> np.ndarray:
        """Preconditioned CG on each column of ``rhs``, one column after the other.

        Args:
            rhs: (N, k) float64 right-hand sides, or a function giving column ``c`` (N,)
                float64 (``columns`` of them): each is then made when its CG starts and let
                go when it ends (a (N, k) array is never held).
            guess: optional (N, k) float64 start (default zero); a float64 array is
                overwritten by the answer (pass a copy to keep it).
            tolerance: the relative residual to reach (default ``rules.relative_tolerance``;
                reported in :attr:`stats`).
            columns: k where ``rhs`` is a function.
            progress: optional ``progress(fraction)``, 0 to 1, as the columns' CG iterations
                go (:class:`SolveProgress`: the digits of the residual gained so far).

        Returns:
            (N, k) float64 solutions; :attr:`stats` says how many iterations they took (the
            most of any column) and whether every column reached the tolerance (an answer
            that did not is returned all the same, reported as not converged).
        """
        start = time.perf_counter()
        if callable(rhs):
            if columns is None:
                raise ValueError("a function of the column needs columns= (how many)")
            column_rhs, k = rhs, int(columns)
        else:
            b = np.asarray(rhs, dtype=np.float64).reshape(self.size, -1)
            column_rhs, k = (lambda c: b[:, c]), b.shape[1]
        # The answer is the guess itself where it is a float64 array (no copy: 134 MB at
        # 1.6M faces), each column updated where it is. One column at a time: CG's vectors
        # are (N,), not (N, k) (~310 MB less at 1.6M faces for k = 3; the same CPU time at
        # 400K faces within the load's noise, bench/README.md).
        x = (np.zeros((self.size, k)) if guess is None
             else np.asarray(guess, dtype=np.float64).reshape(self.size, k))
        tolerance = self.rules.relative_tolerance if tolerance is None else float(tolerance)
        iterations, worst = 0, 0.0
        report = SolveProgress(progress, k)
        for column in range(k):
            b_column = np.asarray(column_rhs(column), dtype=np.float64).reshape(self.size)
            taken = self._column(b_column, x[:, column], tolerance, report.column(column))
            residual = np.linalg.norm(_residual(self.matrix, b_column, x[:, column]))
            worst = max(worst, float(residual) / (float(np.linalg.norm(b_column)) or 1.0))
            iterations = max(iterations, taken)
            del b_column
        self.stats.iterations = iterations
        self.stats.relative_residual = worst
        self.stats.tolerance = tolerance
        self.stats.converged = bool(np.isfinite(x).all() and worst <= 10 * tolerance)
        self.stats.solve_seconds = time.perf_counter() - start
        return x

    def _column(self, b: np.ndarray, x: np.ndarray, tolerance: float,
                observe: Callable[[float, float, float], None]) -> int:
        """CG on ``K x = b`` (N,) from ``x`` (updated in place, a strided column is fine);
        returns its iterations. ``observe(start, residual, target)`` follows its residual."""
        K = self.matrix
        target = tolerance * (float(np.linalg.norm(b)) or 1.0)
        r = _residual(K, b, x)
        start = float(np.linalg.norm(r))
        iterations, _ = conjugate_gradients(
            K.__matmul__, self._precondition, x, r, target, self.rules.max_iterations,
            lambda _, residual: observe(start, residual, target))
        return iterations


def conjugate_gradients(apply: Callable[[np.ndarray], np.ndarray],
                        precondition: Callable[[np.ndarray, np.ndarray | None], np.ndarray],
                        x: np.ndarray, r: np.ndarray, target: float,
                        max_iterations: int,
                        observe: Callable[[int, float], None] | None = None,
                        ) -> tuple[int, float]:
    """Preconditioned conjugate gradients on ``K x = b`` (the one CG loop of the library:
    Eq. 5's iterative answer and the refinement's Gauss-Newton steps).

    Args:
        apply: ``p -> K p`` for (N,) float64 ``p`` (``K`` symmetric positive semi-definite).
        precondition: ``(r, out) -> M^-1 r`` (N,) float64 (the returned array is used);
            ``out`` is a spare (N,) float64 array of the loop's that it may write into and
            return (``None`` the first time). An approximation of ``K^-1`` that may be
            symmetric only to rounding (a single-precision multigrid cycle).
        x: (N,) float64 the start, updated in place (a strided view is fine).
        r: (N,) float64 its residual ``b - K x``, updated in place.
        target: stop once ``||r|| <= target`` (the 2-norm of the recursively updated
            residual).
        max_iterations: the cap on iterations.
        observe: optional ``observe(iterations, ||r||)`` after every iteration (progress).

    Returns:
        (iterations, ||r||) when it stopped: at the target, at the cap, or where a direction
        has no curvature (``p.K p <= 0``) or the preconditioned residual ``r.M^-1 r`` is not
        positive; every iterate from a zero start is a descent direction of ``x.K x / 2 -
        b.x`` all the same.

    The residual is checked before it is preconditioned (no cycle is spent on the last one);
    ``beta`` is the flexible (Polak-Ribiere) ``z.(r - r_previous) / r_previous.z_previous``
    with ``r_previous = r + alpha K p``: a cycle in single precision is symmetric only to
    rounding, which Fletcher-Reeves' ``r.z / r_previous.z_previous`` assumes exactly (the two
    agree in exact arithmetic). Updates of ``x``, ``r`` and ``p`` are in place, in row blocks
    (:data:`~solver.linalg.blocked.ROWS_PER_UPDATE`): no (N,) temporary beyond ``K p`` and
    the preconditioned residual.

    Example:
        >>> import numpy as np, scipy.sparse as sp
        >>> K = sp.diags_array([[-1.0] * 4, [2.0] * 5, [-1.0] * 4], offsets=[-1, 0, 1])
        >>> b, x = np.ones(5), np.zeros(5)
        >>> def jacobi(r, out):
        ...     return r / 2.0
        >>> iterations, residual = conjugate_gradients(K.__matmul__, jacobi, x, b.copy(),
        ...                                            1e-12, 10)
        >>> iterations, bool(np.allclose(K @ x, b))
        (3, True)
    """
    residual = float(np.linalg.norm(r))
    iterations = 0
    if residual <= target or max_iterations <= 0:
        return iterations, residual
    z = precondition(r, None)
    p = z.copy()
    rz = float(r @ z)
    while iterations < max_iterations and rz > 0:
        Kp = apply(p)
        pKp = float(p @ Kp)
        if not pKp > 0:  # a direction of no curvature (or not finite): stop here
            break
        alpha = rz / pKp
        axpy(x, p, alpha, ROWS_PER_UPDATE)
        axpy(r, Kp, -alpha, ROWS_PER_UPDATE)
        iterations += 1
        residual = float(np.linalg.norm(r))
        if observe is not None:
            observe(iterations, residual)
        if residual <= target:
            break
        z = precondition(r, z)
        rz_new = float(r @ z)
        beta = -alpha * float(z @ Kp) / rz
        del Kp                              # the next product is made without it
        axpy(z, p, beta, ROWS_PER_UPDATE)   # p = z + beta p, the new direction in z's array
        p, z = z, p
        rz = rz_new
    return iterations, residual


def _residual(K: sp.spmatrix, b: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``b - K x`` (N,) or (N, k), written into the product's own array."""
    r = K @ x
    np.subtract(b, r, out=r)
    return r
