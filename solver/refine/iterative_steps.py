"""Gauss-Newton steps without a factorization: inexact Newton by preconditioned CG.

Where the refinement's linear solver is iterative (``linear_solver``, chosen by
:class:`solver.linalg.iterative.LinearSolverRules` as for Eq. 5), each fresh Gauss-Newton
step solves the damped matrix ``H + lambda D`` (:func:`solver.refine.damping.damped`) by
conjugate gradients preconditioned by smoothed-aggregation multigrid (pyamg), to a relative
residual of the forcing term (Eisenstat and Walker 1996, choice 2: tight where the gradient
falls fast, loose far from the optimum). No factor and no dense block is formed: the matrix
(its upper triangle in CSR; the hierarchy keeps its own finest copy), the multigrid hierarchy
and a few vectors. The loop is the library's one CG
(:func:`solver.linalg.iterative.conjugate_gradients`, flexible beta, updates in place).

Smoothed aggregation needs the matrix's near-null space: the energy is invariant under rigid
motions, so per vertex the three translations and the three infinitesimal rotations about
the centroid of the positions (elasticity's rigid-body modes; 2 + 1 in the plane). The
hierarchy is kept in single precision (a preconditioner need not be exact; CG's products
and vectors are double; :class:`HierarchyRules`). On every
aggregate, rotations about the global centroid span the local rigid motions of every
connected component. The hierarchy is set up once and reused for the next Gauss-Newton
matrices (only its finest level takes the new matrix; the coarse levels keep their Galerkin
products) while a solve takes at most :attr:`solver.refine.steps.StepRules.cg_resetup_growth`
times the iterations per decade of residual of the first solve after the setup. The decisions
count iterations, never seconds, so that a run takes the same steps on a loaded machine as on
an idle one: a setup is priced as :attr:`~solver.refine.steps.StepRules.cg_setup_iterations`
CG iterations. (A hierarchy reused across steps does as well as a fresh one on these
matrices: on the noisy 100K-face scan, set up before every solve the four solves take 8, 53,
31, 62 iterations, by this rule (which never sets up again here) 8, 53, 32, 62
(``python -m bench.gauss_newton_cg policies 0 --policies always rule``); restarting a solve
with a fresh hierarchy when it ran long cost 42 iterations more at 400K faces, CG's Krylov
space lost. What grows is the iterations a tight tolerance needs: docs/large-meshes.md.)

Each preconditioned residual is projected off the rigid motions of the positions the
matrix was built at (:class:`solver.mesh.rigid_motions.RigidProjection`): the matrix is
definite along them only by the damping's floor, and the coarse solve would otherwise fill
the iterates with huge rigid components that cost nothing in the energy norm CG minimizes.

How the hierarchy is built is data (:class:`HierarchyRules`, :data:`HIERARCHY_RULES`), and
every solve can be watched (:func:`observe_solves`: each solve's matrix, right-hand side,
projection and iterations, for ``bench.gauss_newton_cg``; nothing is kept when no observer
is set).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..linalg.cost import PowerLaw
from ..linalg.hierarchy import smoothed_aggregation
from ..linalg.iterative import (
    LinearSolverRules,
    _multigrid,
    conjugate_gradients,
    digits_share,
)
from .steps import StepRules

REFINEMENT_SOLVER_RULES = LinearSolverRules(
    direct_memory=PowerLaw(per_face=9_800.0, exponent=1.13, base=200 * 1024**2),
    iterative_memory=PowerLaw(per_face=3_600.0, base=200e6))
"""Direct or iterative Gauss-Newton steps (``linear_solver="auto"``): the default answer's
peak memory (process included) with each, against Eq. 5's
(:data:`solver.linalg.iterative.RULES`). Direct: the issue's 3.8 GB at 388K faces and 18.1 GB
at 1.55M (``bench.scale``: 4.2 GB at 400K). By CG: ``bench.scale``'s noisy scans with the
setups' and assemblies' transients in place (bench/README.md "Memory in place"): 440 MB at
100K faces, 1451 MB at 400K, 5487 MB at 1.6M (3.3 KB per face beyond 200 MB; the model is
9-27 % above; 619, 1994 and 9453 MB before). Where Eq. 5's factor fits the memory available
but the refinement's would not, :func:`solver.reconstruct` factorizes Eq. 5 and refines by
CG; the service's admission prices a reconstruction by these models."""


PROLONGATOR_SMOOTHING = ("energy", {"maxiter": 8})
"""pyamg's prolongator smoothing for the Gauss-Newton hierarchy: energy minimization, 8 CG
iterations per column block (pyamg's default is 4). The thin shell's bending modes are what
the prolongators must carry, and on finer meshes they need more smoothing to reach them: on
the noisy scans' last Gauss-Newton matrices (bench.scale's nefertiti, CG to 1e-3 from
zero; ``python -m bench.gauss_newton_cg variants 0``, and ``1``), 81 -> 62 iterations at
100K faces (setup 3.6 -> 5.4 CPU s, CG 4.7 -> 3.9 s) and
179 -> 82 at 400K (setup 15.3 -> 18.4 CPU s, CG 43.0 -> 20.2 s);
2 iterations take 320 at 100K, 16 hardly better than 8 (docs/large-meshes.md)."""


@dataclass(frozen=True)
class HierarchyRules:
    """How the Gauss-Newton matrices' smoothed-aggregation hierarchy is built and cycled
    (keyword arguments of ``pyamg.smoothed_aggregation_solver`` and the cycle of its
    preconditioner). :data:`HIERARCHY_RULES` is the refinement's; ``bench.gauss_newton_cg``
    measures others by the same code path (:class:`Multigrid` takes them).

    Attributes:
        smooth: the prolongator smoothing (:data:`PROLONGATOR_SMOOTHING`).
        max_coarse: the coarsest level's largest order.
        coarse_solver: pyamg's coarse solver.
        cycle: ``"V"``, ``"W"`` or ``"F"``.
        presmoother, postsmoother: pyamg's smoother specifications (None: pyamg's default,
            one symmetric block Gauss-Seidel sweep).
        by_vertex: the finest matrix in (dim, dim) blocks (BSR, one block row per free
            vertex): aggregates take whole vertices and the default smoother inverts each
            vertex's block (False: scalar unknowns, CSR, point Gauss-Seidel on the finest
            level).
        dtype: the hierarchy's precision, ``"float64"`` or ``"float32"`` (CG's products and
            vectors are double either way).
        bounded_setup: the hierarchy set up by
            :func:`solver.linalg.hierarchy.smoothed_aggregation` (pyamg's levels, the
            energy-minimized prolongators computed in place and the coarse matrices formed
            in blocks of rows: the same answer to rounding in a fraction of the memory)
            instead of pyamg's ``smoothed_aggregation_solver``.
        strength_is_matrix: the finest level's strength graph is the (scalar, CSR) matrix
            itself instead of pyamg's copy of it (pyamg's ``symmetric`` strength at theta 0
            keeps every stored entry; only the pattern is read: the same aggregates).
    """

    smooth: tuple[str, dict[str, Any]] = PROLONGATOR_SMOOTHING
    max_coarse: int = 500
    coarse_solver: str = "pinv"
    cycle: str = "V"
    presmoother: tuple[str, dict[str, Any]] | None = None
    postsmoother: tuple[str, dict[str, Any]] | None = None
    by_vertex: bool = False
    dtype: str = "float32"
    bounded_setup: bool = True
    strength_is_matrix: bool = True

    def pyamg_options(self, finest: sp.spmatrix | None = None) -> dict[str, Any]:
        """Keyword arguments of ``pyamg.smoothed_aggregation_solver`` (besides the matrix
        and the near-null space) for the finest matrix ``finest`` (:meth:`finest`). The
        matrix is real symmetric: the restriction is the prolongator's transpose, without
        pyamg's conjugated copy of it."""
        options: dict[str, Any] = {"max_coarse": self.max_coarse,
                                   "coarse_solver": self.coarse_solver, "smooth": self.smooth,
                                   "improve_candidates": None, "symmetry": "symmetric"}
        if self.strength_is_matrix and finest is not None and finest.format == "csr":
            options["strength"] = [("predefined", {"C": finest}), "symmetric"]
        if self.presmoother is not None:
            options["presmoother"] = self.presmoother
        if self.postsmoother is not None:
            options["postsmoother"] = self.postsmoother
        return options

    def smoothers(self) -> tuple[tuple[str, dict[str, Any]], tuple[str, dict[str, Any]]]:
        """The pre- and postsmoother specifications the hierarchy uses (pyamg's default
        where :attr:`presmoother` or :attr:`postsmoother` is None)."""
        default = ("block_gauss_seidel", {"sweep": "symmetric"})
        return self.presmoother or default, self.postsmoother or default

    def finest(self, upper: sp.csr_array, dim: int) -> sp.csr_matrix | sp.bsr_matrix:
        """The hierarchy's finest matrix: the full symmetric matrix whose upper triangle
        (diagonal included) is ``upper`` (N, N), in :attr:`dtype`, as (``dim``, ``dim``)
        blocks where :attr:`by_vertex` (N = free vertices x ``dim``, vertex-major)."""
        full = symmetric_from_upper(upper.astype(self.dtype, copy=False))
        return sp.bsr_matrix(full, blocksize=(dim, dim)) if self.by_vertex else full


HIERARCHY_RULES = HierarchyRules()
"""The refinement's hierarchy: energy-minimizing prolongators (43 CG iterations to 1e-3 on
rocker-arm's noisy Gauss-Newton matrix against 95 with Jacobi-smoothed ones), one V-cycle,
pyamg's smoothers, scalar unknowns in single precision. Aggregated and smoothed per vertex
in double precision (``by_vertex``, ``dtype``) the noisy scans' confirming solves take 49 and
42 CG iterations at 100K and 400K faces against 62 and 76 (``python -m bench.gauss_newton_cg
variants 0`` and ``1``), the whole default answer 19.3 and 120.4 CPU s against 22.9 and
127.8, but at 1.6M faces a confirming solve stalled (relative residual 0.18 after 275
iterations) when the run, not yet converged, had used ~1,850 CPU s against the whole
answer's 1193 by the scalar hierarchy: not chosen (docs/large-meshes.md)."""


@dataclass(frozen=True)
class GaussNewtonSolve:
    """One iterative Gauss-Newton solve as an observer (:func:`observe_solves`) sees it,
    after it ran. The arrays are the solver's own (read them, do not change them).

    Attributes:
        matrix: (N, N) float64 CSR upper triangle of the damped matrix (diagonal included).
        positions: (n_free, dim) float64 free positions it was built at (N = n_free * dim).
        project: the projection off their rigid motions (a callable on (N,) float64).
        rhs: (N,) float64 right-hand side as given to the solve (before the projection).
        tolerance: the relative residual asked for (the forcing term).
        iterations: CG iterations taken; relative_residual: reached; capped: hit the cap.
        fresh: the hierarchy was set up for this matrix (else reused from an earlier one).
        multigrid: the :class:`Multigrid` that preconditioned it.
    """

    matrix: sp.csr_array
    positions: np.ndarray
    project: Callable[[np.ndarray], np.ndarray]
    rhs: np.ndarray
    tolerance: float
    iterations: int
    relative_residual: float
    capped: bool
    fresh: bool
    multigrid: Multigrid


SolveObserver = Callable[[GaussNewtonSolve], None]

_OBSERVER: ContextVar[SolveObserver | None] = ContextVar("gauss_newton_solve_observer",
                                                         default=None)


@contextmanager
def observe_solves(observer: SolveObserver) -> Iterator[None]:
    """Within the ``with`` block (this thread or task), call ``observer`` with a
    :class:`GaussNewtonSolve` after every iterative Gauss-Newton solve (not after solves the
    observer itself makes). Observing changes no answer; without an observer a solve does
    nothing more than one lookup.

    Example:
        >>> seen = []
        >>> with observe_solves(seen.append):
        ...     pass  # e.g. solver.reconstruct(..., linear_solver="iterative")
        >>> seen
        []
    """
    token = _OBSERVER.set(observer)
    try:
        yield
    finally:
        _OBSERVER.reset(token)


def symmetric_from_upper(upper: sp.csr_array) -> sp.csr_matrix:
    """The full symmetric (N, N) CSR matrix (``upper``'s dtype) whose upper triangle
    (diagonal included) is ``upper`` (canonical CSR)."""
    lower = sp.csr_matrix(upper.T)
    full = sp.csr_matrix(upper) + lower
    full.setdiag(full.diagonal() / 2.0)
    full.sort_indices()
    return full


def rigid_modes(X: np.ndarray) -> np.ndarray:
    """(n * dim, k) float64 infinitesimal rigid motions of positions ``X`` (n, dim),
    vertex-major: ``dim`` translations then the rotations about the centroid (3 in 3D, 1 in
    the plane), each column scaled to unit largest entry."""
    n, dim = X.shape
    r = X - X.mean(axis=0) if n else X
    k = dim + (3 if dim == 3 else 1)
    B = np.zeros((n, dim, k))
    for c in range(dim):
        B[:, c, c] = 1.0
    if dim == 3:
        for axis in range(3):  # e_axis x r
            e = np.zeros(3)
            e[axis] = 1.0
            B[:, :, 3 + axis] = np.cross(e, r)
    else:
        B[:, 0, 2], B[:, 1, 2] = -r[:, 1], r[:, 0]
    B = B.reshape(n * dim, k)
    size = np.abs(B).max(axis=0)
    return B / np.where(size > 0, size, 1.0)


def forcing(previous: float | None, gradient_norm: float, previous_norm: float | None,
            loosest: float, tightest: float) -> float:
    """Eisenstat-Walker forcing term (choice 2, gamma 0.9, alpha 2, with its safeguard):
    the relative residual the next Gauss-Newton step's CG stops at.

    Example:
        >>> forcing(None, 1.0, None, 0.1, 1e-6)
        0.1
        >>> round(forcing(0.1, 0.01, 1.0, 0.1, 1e-6), 6)  # gradient 100x down: tight
        9e-05
        >>> forcing(0.5, 0.01, 1.0, 0.1, 1e-6)  # after a loose step the safeguard holds
        0.1
    """
    if previous is None or not previous_norm:
        return loosest
    eta = 0.9 * (gradient_norm / previous_norm) ** 2
    safeguard = 0.9 * previous ** 2
    if safeguard > 0.1:
        eta = max(eta, safeguard)
    return float(min(loosest, max(tightest, eta)))


@dataclass
class CGStats:
    """What the iterative Gauss-Newton solves of one run did (its report's
    ``linear_solver``).

    Attributes:
        iterations: CG iterations of each solve, in order.
        tolerances: the forcing term (relative residual asked for) of each solve.
        residuals: the relative residual each solve reached.
        capped: solves that stopped at the iteration cap before their tolerance.
        setups: multigrid hierarchies set up.
        setup_seconds, solve_seconds: their wall time.
        levels, operator_complexity: of the last hierarchy.
    """

    iterations: list[int] = field(default_factory=list)
    tolerances: list[float] = field(default_factory=list)
    residuals: list[float] = field(default_factory=list)
    capped: int = 0
    setups: int = 0
    setup_seconds: float = 0.0
    solve_seconds: float = 0.0
    levels: int = 0
    operator_complexity: float = 1.0

    def report(self, max_iterations: int) -> dict[str, Any]:
        """JSON-ready summary (``method`` ``"iterative"``)."""
        return {"method": "iterative", "preconditioner": "smoothed aggregation",
                "cg_iterations": list(self.iterations),
                "total_cg_iterations": int(sum(self.iterations)),
                "tolerances": [float(f"{t:.3g}") for t in self.tolerances],
                "relative_residuals": [float(f"{r:.3g}") for r in self.residuals],
                "capped_solves": int(self.capped), "max_iterations": int(max_iterations),
                "converged": self.capped == 0, "setups": int(self.setups),
                "levels": int(self.levels),
                "operator_complexity": round(float(self.operator_complexity), 3),
                "setup_seconds": round(self.setup_seconds, 4),
                "solve_seconds": round(self.solve_seconds, 4)}


class Multigrid:
    """A smoothed-aggregation hierarchy kept across Gauss-Newton matrices of one pattern.

    Args:
        max_iterations: CG's cap per solve.
        resetup_growth: set up again when a solve took more than this many times the
            iterations per decade of residual of the first solve after the last setup.
        setup_iterations: a setup's cost in CG iterations (the price the reuse rules weigh).
        hierarchy: how the hierarchy is built (default :data:`HIERARCHY_RULES`, read when
            the :class:`Multigrid` is made).
    """

    def __init__(self, max_iterations: int, resetup_growth: float,
                 setup_iterations: float, hierarchy: HierarchyRules | None = None) -> None:
        self.max_iterations = max_iterations
        self.resetup_growth = resetup_growth
        self.setup_iterations = setup_iterations
        self.hierarchy = HIERARCHY_RULES if hierarchy is None else hierarchy
        self.stats = CGStats()
        self.progress: Callable[[float], None] | None = None
        """``progress(share)``, 0 to 1, of the digits the solve under way has taken off its
        residual (:func:`~solver.linalg.iterative.digits_share`), after each CG iteration;
        set by the refinement for its run (its progress within a Gauss-Newton step)."""
        self._ml: Any = None
        self._cycle: Any = None
        self._baseline: float | None = None  # iterations per decade, first solve on it
        self._stale = False

    @classmethod
    def of(cls, rules: StepRules) -> Multigrid:
        """The hierarchy the refinement's :class:`~solver.refine.steps.StepRules` ask for
        (``cg_max_iterations``, ``cg_resetup_growth``, ``cg_setup_iterations``)."""
        return cls(rules.cg_max_iterations, rules.cg_resetup_growth, rules.cg_setup_iterations)

    def reset_stats(self) -> None:
        """Count a new run's solves from zero (the hierarchy stays)."""
        self.stats = CGStats(levels=self.stats.levels,
                             operator_complexity=self.stats.operator_complexity)

    def operator(self, upper: sp.csr_array, X_free: np.ndarray,
                 project: Callable[[np.ndarray], np.ndarray]) -> IterativeOperator:
        """The solver of the damped matrix whose upper triangle is ``upper`` (built at the
        free positions ``X_free`` (n_free, dim), whose rigid motions ``project`` removes):
        the hierarchy's finest level takes this matrix, or a new hierarchy is set up where
        the last solves said so."""
        # The hierarchy's own copy of the matrix (HierarchyRules.finest); CG's products use
        # ``upper`` itself (no full copy in CG). The last matrix's copy (or the whole
        # hierarchy, when it is set up again) is let go before the new copy is made.
        fresh = self._ml is None or self._stale or self._ml.levels[0].A.shape != upper.shape
        if fresh:
            self._ml = self._cycle = None
        else:
            self._ml.levels[0].A = None
        finest = self.hierarchy.finest(upper, X_free.shape[1])
        if fresh:
            self._setup(finest, X_free)
        else:
            self._reuse(finest)
        return IterativeOperator(upper, self, project, X_free, fresh)

    def _setup(self, finest: sp.csr_matrix | sp.bsr_matrix, X_free: np.ndarray) -> None:
        pyamg = _multigrid()
        start = time.perf_counter()
        self._ml = None  # its memory is free before the new one is built
        setup = (smoothed_aggregation if self.hierarchy.bounded_setup
                 else pyamg.smoothed_aggregation_solver)
        self._ml = setup(finest, B=rigid_modes(X_free).astype(finest.dtype),
                         **self.hierarchy.pyamg_options(finest))
        self._cycle = self._ml.aspreconditioner(cycle=self.hierarchy.cycle)
        self._baseline, self._stale = None, False
        stats = self.stats
        stats.setups += 1
        stats.setup_seconds += time.perf_counter() - start
        stats.levels = len(self._ml.levels)
        stats.operator_complexity = self._ml.operator_complexity()

    def _reuse(self, finest: sp.csr_matrix | sp.bsr_matrix) -> None:
        """The hierarchy's finest level takes ``finest`` (the coarse levels stay); per
        vertex the smoothers are bound again (block Gauss-Seidel keeps the inverses of the
        finest matrix's diagonal blocks; point Gauss-Seidel keeps nothing)."""
        from pyamg.relaxation.smoothing import change_smoothers

        self._ml.levels[0].A = finest
        if self.hierarchy.by_vertex:
            change_smoothers(self._ml, *self.hierarchy.smoothers())
            self._cycle = self._ml.aspreconditioner(cycle=self.hierarchy.cycle)

    def cycle(self, r: np.ndarray) -> np.ndarray:
        """One cycle (the hierarchy's precision) from a zero guess on ``r`` (N,) float64."""
        return np.asarray(self._cycle @ r.astype(self._ml.levels[0].A.dtype, copy=False),
                          dtype=np.float64)

    def solved(self, iterations: int, decades: float, capped: bool) -> None:
        """Note a solve: ``iterations`` for ``decades`` decades of residual. The first on a
        hierarchy sets its baseline rate (iterations per decade); the hierarchy
        is stale (set up again before the next solve) where the solve hit the cap, or took
        more than ``resetup_growth`` times the baseline rate and the iterations beyond the
        baseline cost more than a setup (``setup_iterations``).

        Example:
            >>> mg = Multigrid(300, 2.0, setup_iterations=50)
            >>> mg.solved(20, 2.0, False)  # baseline: 10 per decade
            >>> mg.solved(90, 3.0, False)  # 30 per decade: 60 iterations beyond, > 50
            >>> mg._stale
            True
        """
        rate = iterations / max(decades, 0.5)
        if self._baseline is None:
            self._baseline = max(rate, 1.0)
            return
        extra = (rate - self._baseline) * max(decades, 0.5)
        if capped or (rate > self.resetup_growth * self._baseline
                      and extra > self.setup_iterations):
            self._stale = True


class IterativeOperator:
    """``K^-1 v`` by preconditioned CG for one damped Gauss-Newton matrix ``K`` (the
    refinement's "factor" on the iterative path; :attr:`precision` says so).

    Args:
        upper: (N, N) float64 CSR upper triangle of ``K`` (diagonal included).
        multigrid: the :class:`Multigrid` whose hierarchy preconditions it.
        project: the projection off the rigid motions of the positions ``K`` was built at.
        positions: (n_free, dim) float64 those positions (for observers).
        fresh: the hierarchy was set up for ``K`` (for observers).

    Attributes:
        tolerance: the relative residual the next :meth:`solve` stops at (the forcing term).
    """

    precision = "iterative"

    def __init__(self, upper: sp.csr_array, multigrid: Multigrid,
                 project: Callable[[np.ndarray], np.ndarray],
                 positions: np.ndarray | None = None, fresh: bool = False) -> None:
        self.matrix = upper
        self._diagonal = upper.diagonal()
        self.multigrid = multigrid
        self.project = project
        self.positions = positions
        self.fresh = fresh
        self.tolerance = 1e-2

    def solve(self, b: np.ndarray) -> np.ndarray:
        """(N,) float64 approximate ``K^-1 b`` without rigid motions: CG from zero until
        ``||K x - b|| <= tolerance ||b||`` or the cap (then counted as capped; the
        iterate is returned all the same: every CG iterate from zero is a descent
        direction of the model)."""
        start = time.perf_counter()
        mg, U, P, d = self.multigrid, self.matrix, self.project, self._diagonal
        given = b
        b = P(np.asarray(b, dtype=np.float64))
        x = np.zeros_like(b)
        norm_b = float(np.linalg.norm(b))
        target = self.tolerance * norm_b
        report = mg.progress
        iterations, residual = conjugate_gradients(
            lambda p: U @ p + U.T @ p - d * p, lambda r, out: P(mg.cycle(r)), x, b.copy(),
            target, mg.max_iterations,
            None if report is None else lambda _, r: report(digits_share(norm_b, r, target)))
        capped = residual > target
        relative = residual / norm_b if norm_b else 0.0
        stats = mg.stats
        stats.iterations.append(iterations)
        stats.tolerances.append(self.tolerance)
        stats.residuals.append(relative)
        stats.capped += int(capped)
        stats.solve_seconds += time.perf_counter() - start
        mg.solved(iterations, -math.log10(max(relative, 1e-300)), capped)
        observer = _OBSERVER.get()
        if observer is not None:  # not observed itself: it may solve (a replay)
            token = _OBSERVER.set(None)
            try:
                observer(GaussNewtonSolve(U, self.positions, P, given, self.tolerance,
                                          iterations, relative, capped, self.fresh, mg))
            finally:
                _OBSERVER.reset(token)
        return x
