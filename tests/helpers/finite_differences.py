"""Directional finite differences of a function of the forms against its vector-Jacobian
product (the tests of :func:`solver.reconstruct_vjp`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

STEPS = (1e-5, 1e-6)
"""Central-difference step sizes (relative to the lengths; radians for the angles)."""


def directional_errors(L: np.ndarray, A: np.ndarray, grads: tuple[np.ndarray, np.ndarray],
                       rng: np.random.Generator, loss: Callable[[np.ndarray, np.ndarray], float],
                       directions: int) -> np.ndarray:
    """(len(STEPS),) max over ``directions`` random directions (dL = N(0,1) L, dA = N(0,1))
    of |central difference of ``loss`` - (grad_L . dL + grad_A . dA)| / |the latter|, one
    value per step size of :data:`STEPS`."""
    grad_L, grad_A = grads
    errors = []
    for _ in range(directions):
        dL = rng.standard_normal(len(L)) * L
        dA = rng.standard_normal(len(A))
        predicted = grad_L @ dL + grad_A @ dA
        errors.append([abs((loss(L + h * dL, A + h * dA) - loss(L - h * dL, A - h * dA))
                           / (2 * h) - predicted) / abs(predicted) for h in STEPS])
    return np.max(errors, axis=0)
