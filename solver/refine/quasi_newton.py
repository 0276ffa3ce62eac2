"""Quasi-Newton steps on a kept factorization: L-BFGS with the factor as initial Hessian.

Between factorizations of the Gauss-Newton matrix, :mod:`solver.refine` takes steps that
cost one back-substitution each: L-BFGS (Nocedal and Wright, Alg. 7.4) whose initial
Hessian is the factor (Liu, Bouaziz and Kavan 2017, "Quasi-Newton methods for real-time
simulation of hyperelastic materials"), corrected along the last steps by the gradient
changes they produced. :class:`QuasiNewtonMemory` keeps those steps.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from .normal_equations import GaussNewtonSystem


class QuasiNewtonMemory:
    """The last ``size`` steps ``s`` and gradient changes ``y`` since the factor was built,
    for L-BFGS's two-loop recursion (Nocedal and Wright, Alg. 7.4); with ``size`` 0 the
    steps are plain back-substitutions with the factor (frozen Gauss-Newton steps).

    The initial Hessian is the factor's matrix ``H`` scaled by ``gamma = s.y / s.H s`` of
    the newest pair: the curvature E showed along the last step over the one the factor
    predicted (the scaling of Nocedal and Wright's (7.20) with ``H`` for the identity). A
    session's factor comes from an earlier drag's shape; unscaled, its steps overshot by
    2x, so that half of the later drags' steps were halved by the line search (rocker-arm,
    drags 2-5: 29 steps; scaled: 24, to the same or a lower E; ``python -m bench.refinement
    --sections drag`` prints the iterations per drag).
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self.pairs: list[tuple[np.ndarray, np.ndarray, float]] = []
        self._last: tuple[np.ndarray, np.ndarray, GaussNewtonSystem, sp.csr_array] | None = None
        self.gamma = 1.0

    def clear(self) -> None:
        """Forget the pairs (a new factor was built)."""
        self.pairs.clear()
        self.gamma = 1.0

    def moved(self, step: np.ndarray, gradient: np.ndarray, system: GaussNewtonSystem,
              model: sp.csr_array) -> None:
        """A step ``step`` was taken from where the gradient was ``gradient``; ``model`` is
        the matrix of the factor (for the curvature it gave the step, computed when the
        gradient after the step is observed: a run's last step never is)."""
        if self.size:
            self._last = (step, gradient, system, model)

    def observe(self, gradient: np.ndarray) -> None:
        """The gradient after the last step: keep the pair where it has positive curvature."""
        if self._last is None or not self.size:
            return
        s, before, system, matrix = self._last
        self._last = None
        y = gradient - before
        sy = float(np.einsum("i,i->", s, y))
        if sy > 1e-12 * float(np.sqrt(np.einsum("i,i->", y, y) * np.einsum("i,i->", s, s))):
            self.pairs.append((s, y, 1.0 / sy))
            del self.pairs[:len(self.pairs) - self.size]
            model = system.quadratic_form(matrix, s)
            if model > 0:  # the curvature along s against the factor's model of it
                self.gamma = sy / model

    def inverse_hessian(self, solve: Callable[[np.ndarray], np.ndarray],
                        g: np.ndarray) -> np.ndarray:
        """``H^-1 g`` of L-BFGS with ``solve`` (``v -> H_0^-1 v``) as ``H_0^-1``."""
        q = g.copy()
        alphas = []
        for s, y, rho in reversed(self.pairs):
            a = rho * float(np.einsum("i,i->", s, q))
            alphas.append(a)
            q -= a * y
        r = solve(q) / self.gamma
        for (s, y, rho), a in zip(self.pairs, reversed(alphas), strict=True):
            r += (a - rho * float(np.einsum("i,i->", y, r))) * s
        return r
