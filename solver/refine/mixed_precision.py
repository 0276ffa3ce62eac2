"""A Gauss-Newton matrix factorized in single precision, its solves refined in double.

PARDISO factorizes the refinement's Gauss-Newton matrix in float32 in about half the time
of float64 (rocker-arm, 20K faces: 0.04-0.05 s against 0.08-0.12 s; armadillo, 86K: 0.30
against 0.54 s; ``python -m bench.gauss_newton_factor``). A float32 factor's answers are
off by ~6e-8 times the matrix's condition, so each solve takes one step of iterative
refinement: the residual in float64, the correction from the same factor (Higham,
"Accuracy and Stability of Numerical Algorithms", 2nd ed., Sec. 12.1). Its correction is
about the first answer's relative error, and the corrected answer's error about its
square; a correction over ``tolerance`` of the answer raises :class:`ImpreciseSolveError`
and the caller factorizes in double precision instead.

The refinement's matrix is singular along the rigid motions of a component no handle holds,
up to its relative damping of 1e-9, below float32's resolution: the float32 pivots of those
motions are rounding noise, and the solutions' components along them, however large, are
projected off by the caller (:mod:`solver.mesh.rigid_motions`); where such a pivot comes out
negative (the knight of the tests) PARDISO refuses the factor and the caller factorizes in
double precision. Two ways of making those pivots definite were measured and left out: a
uniform lift of the diagonal holds back the soft bending modes below it (1e-6 of the
diagonal: the refinement step then corrected rocker-arm's solves by over 10%), and holding
a gauge of six coordinates per component leaves nearly rigid modes whose float32 errors the
projection does not remove (armadillo: corrections of 20%).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from ..linalg import SingularSystemError, factorize, upper_symmetric_product

FLOAT32_MAX = float(np.finfo(np.float32).max)


class ImpreciseSolveError(ArithmeticError):
    """A single-precision solve's refinement step corrected it by more than the tolerance:
    the factor is too inexact for this matrix (factorize it in double precision)."""


class SinglePrecisionFactor:
    """Single-precision factor of an SPD matrix ``K``, its solves refined in double.

    Args:
        matrix: (N, N) upper triangle of ``K`` (canonical float64 CSR, every diagonal entry
            stored, as :func:`solver.linalg.factorize` reads with ``triangle="upper"``).
        backend: a backend name; only PARDISO factorizes in single precision (others
            factorize in double, refined the same way).
        tolerance: largest relative correction (2-norm) of a solve's refinement step.

    Attributes:
        precision: ``"single"`` (``"double"`` where the backend ignores the precision).
        matrix: the upper triangle of ``K``, as given.

    Raises:
        SingularSystemError: the backend found ``K`` not positive definite in single
            precision.

    Example:
        >>> import numpy as np
        >>> import scipy.sparse as sp
        >>> K = sp.csr_array([[4.0, 1.0], [0.0, 3.0]])  # the upper triangle of [[4,1],[1,3]]
        >>> factor = SinglePrecisionFactor(K)
        >>> np.allclose(factor.solve(np.array([5.0, 4.0])), [1.0, 1.0], atol=1e-9)
        True
    """

    def __init__(self, matrix: sp.csr_array, backend: str = "auto",
                 tolerance: float = 0.1) -> None:
        self._factor = factorize(matrix, backend, triangle="upper", precision="single")
        self.matrix = matrix
        self.precision = self._factor.precision
        self.tolerance = tolerance

    def solve(self, v: np.ndarray,
              project: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
        """``K^-1 v`` (N,), by one float32 solve and one refinement step.

        Args:
            v: (N,) float64 right-hand side.
            project: optional linear map applied to each back-substitution's answer (the
                projection off the rigid motions, where ``K`` is nearly singular along
                them: :class:`solver.mesh.rigid_motions.RigidProjection`).

        Returns:
            (N,) float64 solution (two back-substitutions).

        Raises:
            ImpreciseSolveError: the refinement step changed the answer by more than
                ``tolerance`` of it (relative 2-norm), or it is not finite.
        """
        def solved(rhs: np.ndarray) -> np.ndarray:
            if not np.abs(rhs).max(initial=0.0) < FLOAT32_MAX:  # NaN too
                raise ImpreciseSolveError("a right-hand side beyond float32's range")
            try:
                x = self._factor.solve(rhs)
            except SingularSystemError as error:  # a float32 answer that is not finite
                raise ImpreciseSolveError(f"a single-precision solve failed: {error}") from error
            return x if project is None else project(x)

        x = solved(v)
        correction = solved(v - upper_symmetric_product(self.matrix, x))
        if not (np.linalg.norm(correction) <= self.tolerance * np.linalg.norm(x)):
            raise ImpreciseSolveError(
                f"a single-precision solve's refinement corrected it by "
                f"{np.linalg.norm(correction) / np.linalg.norm(x):.3g} of its size")
        return x + correction
