"""Eq. (5)'s constrained linear system: ``K`` with hard unknowns eliminated and soft penalties
added, solved by a factorization or by multigrid-preconditioned CG (:class:`ConstrainedSystem`;
the matrix itself is assembled in :mod:`solver.linear.system`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from ..linalg import Factorization, factorize
from ..linalg.iterative import RULES, IterativeSolver, LinearSolverRules


class ConstrainedSystem:
    """``K`` with hard unknowns eliminated and soft penalties added, factorized once.

    Hard unknowns are eliminated symmetrically in place: their rows and columns are
    cleared except for the diagonal, and their coupling to the free unknowns moves to the
    right-hand side. The factorized matrix keeps its size N, so no index remapping or
    sub-matrix copy is needed. The cleared entries stay stored as explicit zeros, so the
    sparsity pattern is that of ``K`` whatever the constraint set: a new handle set on the
    same mesh reuses the analysis of the previous one (:mod:`solver.linalg` caches it per
    pattern; ``analysis`` says whether it did). ``solve(hard_values, soft_values)`` only
    back-substitutes, so handle drags reuse the factorization (the paper's
    prefactorization, Sec. 5). The constrained unknowns and soft weights are fixed at
    construction; their target values may change per solve.

    Args:
        K: (N, N) sparse ``A^T W A``, or a function that hands it over: the caller then
            holds no reference while this constructor runs (arguments stay referenced by
            the caller's frame until the call returns), so K is freed as soon as the
            system has made its own constrained copy, before the factorization or the
            multigrid setup.
        hard_columns: (h,) int64 unknowns fixed exactly.
        soft_columns: (s,) int64 unknowns pulled towards targets.
        soft_weights: (s,) float64 > 0 their penalty weights.
        backend: sparse factorization backend (:func:`solver.linalg.factorize`).
        groups: optional (N,) int64 ordering hint (:func:`solver.linear.system.unknown_groups`).
        method: ``"direct"`` (factorize) or ``"iterative"`` (multigrid-preconditioned CG,
            :class:`solver.linalg.iterative.IterativeSolver`: no factor, for large meshes).
        near_null: (N, k) near-null space of ``K`` for the iterative method
            (:func:`solver.linear.system.near_null_space`), or a function that hands it
            over (its array, in the preconditioner's precision, is then used in place, not
            copied: 90 MB at 1.6M faces); None: the constant.
        rules: the iterative method's tolerance and iteration limit.

    Attributes:
        method: ``"direct"`` or ``"iterative"``.
        iterative: the :class:`~solver.linalg.iterative.IterativeSolver` (None when direct).

    Raises:
        SingularSystemError: the constrained matrix is singular.
        BackendUnavailableError: the backend is not installed.
    """

    def __init__(self, K: sp.spmatrix | Callable[[], sp.spmatrix], hard_columns: np.ndarray,
                 soft_columns: np.ndarray,
                 soft_weights: np.ndarray, backend: str = "auto",
                 groups: np.ndarray | None = None, method: str = "direct",
                 near_null: np.ndarray | Callable[[], np.ndarray | None] | None = None,
                 rules: LinearSolverRules = RULES) -> None:
        owned = callable(K)  # handed over: this constructor may reuse its arrays
        if owned:
            K = K()
        N = K.shape[0]
        self.size = N
        self.hard_columns = np.asarray(hard_columns, dtype=np.int64)
        self.soft_columns = np.asarray(soft_columns, dtype=np.int64)
        self.soft_weights = np.asarray(soft_weights, dtype=np.float64)
        hard = np.zeros(N, dtype=bool)
        hard[self.hard_columns] = True
        # Penalties of soft constraints, and 1 on hard diagonals (unused vertices have none).
        diagonal = np.bincount(self.soft_columns, weights=self.soft_weights,
                               minlength=N).astype(np.float64) + hard
        K = _plus_diagonal(K, diagonal, owned)
        self.K_hard_rows = K[self.hard_columns]            # (h, N): coupling to the rhs
        # Entries of hard rows or columns are cleared, but for the hard diagonals. K is this
        # constructor's own sum, so its values are cleared in place; the masks are per
        # nonzero booleans (no int64 row index per nonzero: 0.6 GB at 1.6M faces).
        cols = K.indices
        hard_row = np.repeat(hard, np.diff(K.indptr))
        clear = hard_row | hard[cols]
        if len(self.hard_columns):
            # The hard diagonals (a hard row's entry in its own column) stay.
            row_of = np.repeat(np.flatnonzero(hard), np.diff(K.indptr)[hard])
            clear[np.flatnonzero(hard_row)[row_of == cols[hard_row]]] = False
            del row_of
        K.data[clear] = 0.0
        del hard_row, clear
        # Explicit zeros kept on purpose (see the class docstring).
        reduced = K
        del K
        self.hard_diagonal = reduced.diagonal()[self.hard_columns]
        self.method = method
        self.iterative: IterativeSolver | None = None
        self.factor: Factorization | None = None
        if method == "iterative":
            reduced.eliminate_zeros()  # the multigrid's strength graph reads the pattern
            handed = callable(near_null)
            candidates = near_null() if handed else near_null
            del near_null
            if candidates is not None:
                # In the preconditioner's precision: the solver takes it without a copy (a
                # handed-over array of that precision is this system's own already).
                candidates = (np.asarray if handed else np.array)(
                    candidates, dtype=rules.preconditioner_dtype)
                candidates[self.hard_columns] = 0.0
            self.iterative = IterativeSolver(reduced, candidates, rules)
        elif method == "direct":
            self.factor = factorize(reduced, backend, assume_symmetric=True, groups=groups)
        else:
            raise ValueError(f"unknown method {method!r}; expected 'direct' or 'iterative'")

    @property
    def backend(self) -> str:
        """The backend that factorized the system (``"none"`` when iterative)."""
        return "none" if self.factor is None else self.factor.backend

    @property
    def analysis(self) -> str:
        """``"cached"`` or ``"computed"``: see :class:`solver.linalg.Factorization`
        (``"none"`` when iterative)."""
        return "none" if self.factor is None else self.factor.analysis

    def linear_solver_report(self) -> dict[str, object]:
        """``{"method": "direct", "backend"}`` or the iterative solve's statistics
        (:meth:`solver.linalg.iterative.IterativeStats.report`: iterations, final relative
        residual, converged)."""
        if self.iterative is not None:
            return self.iterative.stats.report()
        return {"method": "direct", "backend": self.backend}

    def solve(self, hard_values: np.ndarray, soft_values: np.ndarray,
              guess: np.ndarray | None = None, tolerance: float | None = None,
              overwrite_guess: bool = False,
              progress: Callable[[float], None] | None = None) -> np.ndarray:
        """Solve for new constraint targets (back-substitution only when direct).

        Args:
            hard_values: (h, 3) float64 values of the hard unknowns.
            soft_values: (s, 3) float64 targets of the soft unknowns.
            guess: optional (N, 3) float64 start of the iterative method (ignored when
                direct).
            tolerance: the iterative method's relative residual (default: its rules';
                ignored when direct).
            overwrite_guess: the iterative method may use ``guess`` (a float64 (N, 3)
                array) as its iterate, overwriting it, instead of a copy.
            progress: optional ``progress(fraction)``, 0 to 1, as the iterative method's CG
                goes (:class:`solver.linalg.iterative.SolveProgress`; not called when
                direct).

        Returns:
            (N, 3) float64 unknowns, one column per coordinate.
        """
        hard_values = np.asarray(hard_values, dtype=np.float64).reshape(-1, 3)
        soft_values = np.asarray(soft_values, dtype=np.float64).reshape(-1, 3)
        if self.iterative is not None:
            start = None
            if guess is not None:
                start = (np.asarray(guess, dtype=np.float64) if overwrite_guess
                         else np.array(guess, dtype=np.float64))
                start[self.hard_columns] = hard_values
            # Each coordinate's right-hand side made when its CG starts (N,), not (N, 3).
            u = self.iterative.solve(lambda c: self._rhs(hard_values[:, c:c + 1],
                                                         soft_values[:, c:c + 1])[:, 0],
                                     start, tolerance, columns=3, progress=progress)
            u[self.hard_columns] = hard_values
            return u
        assert self.factor is not None
        u = self.factor.solve(self._rhs(hard_values, soft_values))
        u[self.hard_columns] = hard_values
        return u

    def _rhs(self, hard_values: np.ndarray, soft_values: np.ndarray) -> np.ndarray:
        """(N, k) right-hand sides for (h, k) hard values and (s, k) soft targets."""
        rhs = np.zeros((self.size, hard_values.shape[1]))
        np.add.at(rhs, self.soft_columns, self.soft_weights[:, None] * soft_values)
        rhs -= self.K_hard_rows.T @ hard_values
        rhs[self.hard_columns] = self.hard_diagonal[:, None] * hard_values
        return rhs


def _plus_diagonal(K: sp.spmatrix, diagonal: np.ndarray, owned: bool) -> sp.csr_matrix:
    """``K + diag(diagonal)`` as a CSR matrix of the caller's own.

    ``owned``: no one else holds ``K`` (handed over to :class:`ConstrainedSystem`). A CSC
    ``K`` (symmetric: its CSC arrays are the CSR arrays of ``K^T = K``) is then taken as it
    is and its stored diagonal updated in place, where every diagonal entry is stored (not
    so with unused vertices). Otherwise a new matrix is built: a CSR copy and the sum, two
    transient copies of ``K`` (24 bytes per nonzero, 1.9 GB at 1.6M faces).
    """
    if owned and K.format == "csc":
        csr = sp.csr_matrix((K.data, K.indices, K.indptr), shape=K.shape, copy=False)
        csr.sum_duplicates()  # sorted rows, in place (a product's rows are not)
        current = csr.diagonal()
        if bool((current != 0).all()):
            current += diagonal
            csr.setdiag(current)  # every entry stored: written in place, no new pattern
            return csr
    K = (sp.csr_matrix(K) + sp.diags(diagonal)).tocsr()
    K.sum_duplicates()
    return K
