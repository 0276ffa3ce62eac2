"""The refinement's residuals, one kind per group, with targets that can be replaced in place.

:class:`solver.refine.form_energy.FormEnergy` sums the squares of these groups. Each group
has a *structure* (which vertices each residual touches: fixed for a connectivity, its cap
faces and needle ties) and *values* (target lengths and angles, weights, the mean length
``s``) that :meth:`set` replaces without touching the structure: the rows of a blend
sequence change only the values (:meth:`solver.refine.Refiner.retarget`), so the
Gauss-Newton pattern built for the structure (:mod:`solver.refine.normal_equations`) stays.
A single refinement builds the same groups once and sets their values once: one code path.

Every group has ``vertices`` (rows, q) int64, ``hinge`` (its rows are hinges whose other
vertex pairs are edges of the length group), ``evaluate(X, grad=True) -> (r (rows,), G (rows,
q, dim) or None)`` (weighted residuals at positions ``X`` (n, dim) and their gradients with
respect to the row's ``q`` vertices) and ``curvature`` (None, or ``curvature(X, r) -> (rows
(k,) int64, M (k, dim, dim))``: the part ``r ∇²r`` of the Hessian of ``r^2 / 2`` that the
Gauss-Newton matrix keeps for some rows of a two-vertex group, ``+M`` on the blocks (0, 0) and
(1, 1), ``-M`` on (0, 1)).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..mesh.embedding_geometry import edge_vectors, hinge_angles, signed_areas
from ..mesh.metrics import wrap_angle
from .energy_weights import AREA_FLOOR

Evaluate = Callable[..., tuple[np.ndarray, np.ndarray | None]]
"""``evaluate(X, grad=True) -> (r (rows,), G (rows, q, dim) or None)``."""

Curvature = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``curvature(X, r) -> (rows (k,) int64, M (k, dim, dim))`` (see the module docstring)."""

DEGENERATE = 1e-12  # floor of |N|^2 / s^4 for the dihedral gradient of collapsed faces
NEEDLE_STIFFNESS = 1e4
"""Stiffness of a needle edge's relative length over a mean edge's (``(s / L)^2``): the
refinement's damping does not scale with the diagonal of its vertices
(:meth:`solver.refine.Refiner._damped_factor`). Edges 1e-4 of the mean long (the held-out
irregular mesh of issue 19 and bench.refinement's irregular cases) are 1e8 times as stiff;
the face of the tests has edges 0.04 of the mean long (600 times), where capping the
damping cost a session's kept-factor drags 30% in energy."""
STRETCH_CURVATURE = 100.0
"""Gauss-Newton drops ``r ∇²r`` from the Hessian of a residual's ``r^2 / 2`` as small beside
``∇r ∇r^T``. Across a stretched edge (``r > 0``) that term, ``r / (L l) (I - u u^T)``, is
the edge's only stiffness, and on an edge far shorter than the mesh's mean it is not small:
without it the vertex of a needle edge swings across the edge between iterations, and
the models of the iterations after are refused or crawl (rocker-arm with 30 edges split to
1e-4 of their length, noisy angles: 7 factorizations, 4 with it, ``python -m
bench.refinement --sections time``; the torus with 20 of tests/solver/test_refine.py: 8
and 4). The refinement keeps it where it is at least this many times a mean edge's
stiffness ``1 / s^2``: in practice needle edges only, as a 100-fold smaller ratio also
changed the planar refinement of the beetle, whose stretched edges are long (16 -> 29
iterations with this constant at 1; ``python -m bench.refinement --sections
parameterize``). Never where ``r < 0``: that part is negative and would make the matrix
indefinite."""


class ResidualGroup:
    """One kind of residual (see the module docstring); subclasses set the values."""

    hinge = False
    curvature: Curvature | None = None

    def __init__(self, vertices: np.ndarray) -> None:
        self.vertices = vertices

    def evaluate(self, X: np.ndarray, grad: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        raise NotImplementedError


class LengthResiduals(ResidualGroup):
    """``sqrt(w_e) (l_e / L_e - 1)`` of edges (E, 2): :meth:`set` the targets."""

    def __init__(self, edges: np.ndarray) -> None:
        super().__init__(edges)
        self.curvature = self._curvature

    def set(self, lengths: np.ndarray, weights: np.ndarray, scale: float) -> None:
        """Target lengths (E,) > 0, weights (E,) >= 0 (0: a tie's rigid edge) and the mean
        target length ``scale``."""
        self.L, self.w = lengths, np.sqrt(weights)
        self.stiff = STRETCH_CURVATURE / scale**2
        needles = weights / lengths**2 >= NEEDLE_STIFFNESS / scale**2
        self.needle_vertices = np.unique(self.vertices[needles].ravel())

    def errors(self, r: np.ndarray, X: np.ndarray) -> np.ndarray:
        """The relative length errors ``l / L - 1`` (E,) of ``X`` whose residuals are ``r``
        (unweighted, so rigid edges, of weight 0, are measured on ``X``)."""
        w = self.w
        if (w == 1.0).all():
            return r
        out = np.divide(r, w, out=np.zeros_like(r), where=w > 0)
        rigid = np.flatnonzero(w == 0)
        if len(rigid):
            _, length = edge_vectors(X, self.vertices[rigid])
            out[rigid] = length / self.L[rigid] - 1.0
        return out

    def evaluate(self, X: np.ndarray, grad: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        d, length = edge_vectors(X, self.vertices)
        r = self.w * (length / self.L - 1.0)
        if not grad:
            return r, None
        unit = d * (self.w / (np.where(length > 0, length, 1.0) * self.L))
        G = np.empty((len(r), 2, X.shape[1]))
        G[:, 1] = unit.T
        np.negative(G[:, 1], out=G[:, 0])
        return r, G

    def _curvature(self, X: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # r ∇²r = w² (l/L - 1) / (L l) (I - u u^T) across a stretched edge (l from r);
        # kept where it is at least STRETCH_CURVATURE x a mean edge's 1 / s^2.
        L, w, edges = self.L, self.w, self.vertices
        length = L * (1.0 + r / np.where(w > 0, w, 1.0))  # (w = 0: a tie's edge)
        c = np.maximum(r, 0.0) * w / (L * np.maximum(length, L))
        rows = np.flatnonzero(c >= self.stiff)
        d = X[edges[rows, 1]] - X[edges[rows, 0]]
        u = d / np.linalg.norm(d, axis=1)[:, None]
        M = np.eye(X.shape[1]) - u[:, :, None] * u[:, None, :]
        return rows, c[rows, None, None] * M


HINGE_BLOCK = 1 << 14
"""Hinges :meth:`HingeResiduals.evaluate` measures at once (its transient memory is that of
a block: ~60 MB less at 100K faces, ~1 GB at 1.6M, for the same values)."""


class HingeResiduals(ResidualGroup):
    """``sqrt(w_e) wrap(theta_e - Theta_e)`` of hinges (k, 4) ``[i, j, a, b]``."""

    hinge = True

    def set(self, target: np.ndarray, weights: np.ndarray, scale: float) -> None:
        """Target angles (k,), weights (k,) > 0 and the mean target length ``scale``."""
        self.target, self.w = target, np.sqrt(weights)
        self.floor = DEGENERATE * scale**4

    def errors(self, r: np.ndarray) -> np.ndarray:
        """The angle errors ``wrap(theta - Theta)`` (k,) whose residuals are ``r``."""
        return r / self.w

    def evaluate(self, X: np.ndarray, grad: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        # In blocks of HINGE_BLOCK hinges written into the answer: the angles' and
        # gradients' temporaries (~30 arrays of a block's length) stay a few MB.
        k = len(self.vertices)
        r = np.empty(k)
        G = np.empty((k, 4, X.shape[1])) if grad else None
        for lo in range(0, k, HINGE_BLOCK):
            part = slice(lo, lo + HINGE_BLOCK)
            theta, g = hinge_angles(X, self.vertices[part], self.floor, grad)
            w = self.w[part]
            r[part] = w * wrap_angle(theta - self.target[part])
            if G is not None:
                np.multiply(w[:, None, None], g, out=G[part])
        return r, G


class CapResiduals(ResidualGroup):
    """``(x_c - (1 - t) x_a - t x_b) / L_ab`` of cap faces, one row per coordinate
    (:func:`solver.refine.form_energy.cap_faces`; ``corners`` (k, 3) ``[a, b, c]``)."""

    def __init__(self, corners: np.ndarray, dim: int) -> None:
        super().__init__(np.repeat(corners, dim, axis=0))
        self.corners, self.dim = corners, dim

    def set(self, coefficients: np.ndarray) -> None:
        """The residuals' weighted coefficients (k, 3) of ``[x_a, x_b, x_c]``."""
        dim = self.dim
        self.coefficients = coefficients
        G = coefficients[:, None, :, None] * np.eye(dim)[None, :, None, :]  # (k, dim, 3, dim)
        self.G = G.reshape(-1, 3, dim)

    def evaluate(self, X: np.ndarray, grad: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        r = np.einsum("kc,kcd->kd", self.coefficients, X[self.corners])
        return r.ravel(), (self.G if grad else None)


class AreaResiduals(ResidualGroup):
    """One-sided signed-area residuals of planar faces (m, 3) (dim 2): only faces shrunk
    below :data:`AREA_FLOOR` of their area, or flipped, pay; the others are left to the
    lengths (a two-sided area term costs length accuracy)."""

    def set(self, target_areas: np.ndarray, weight: float, scale: float) -> None:
        """Target areas (m,) (from the target lengths), ``gamma`` and ``scale``."""
        area0 = np.maximum(target_areas, DEGENERATE * scale**2)
        self.w = np.sqrt(weight * area0 / area0.mean())  # area-weighted like the lengths
        self.c = self.w / area0

    def evaluate(self, X: np.ndarray, grad: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        area, G = signed_areas(X, self.vertices, grad)
        r = np.minimum(self.c * area - AREA_FLOOR * self.w, 0.0)
        if G is None:
            return r, None
        return r, np.where(r < 0, self.c, 0.0)[:, None, None] * G


class SoftPositionResiduals(ResidualGroup):
    """``sqrt(w_v) (x_v - p_v) / s`` of soft position handles, one row per coordinate."""

    def __init__(self, handle_vertices: np.ndarray, weights: np.ndarray, positions: Any,
                 dim: int) -> None:
        super().__init__(np.repeat(handle_vertices[:, None], dim, axis=0))
        self.handle_vertices, self.weights, self.dim = handle_vertices, weights, dim
        self.positions = np.array(positions, dtype=np.float64)

    def set(self, scale: float) -> None:
        """The mean target length ``scale``."""
        self.w = np.sqrt(self.weights) / scale
        eye = np.broadcast_to(np.eye(self.dim), (len(self.w), self.dim, self.dim))
        self.G = (self.w[:, None, None] * eye).reshape(-1, 1, self.dim)

    def evaluate(self, X: np.ndarray, grad: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        r = (self.w[:, None] * (X[self.handle_vertices] - self.positions)).ravel()
        return r, (self.G if grad else None)


class FrameResiduals(ResidualGroup):
    """``sqrt(w_t) (x_tc - x_t0 - E_tc) / s`` of orientation handles: the faces' edge
    vectors against their targets ``frame_edges`` (q, 2, dim), one row per coordinate."""

    def __init__(self, faces: np.ndarray, weights: np.ndarray, frame_edges: Any,
                 dim: int) -> None:
        self.pairs = np.concatenate([faces[:, [0, 1]], faces[:, [0, 2]]])     # (2q, 2)
        super().__init__(np.repeat(self.pairs, dim, axis=0))
        self.weights, self.dim = weights, dim
        self.frame_edges = np.array(frame_edges, dtype=np.float64)

    def set(self, scale: float) -> None:
        """The mean target length ``scale``."""
        dim = self.dim
        self.w = np.tile(np.sqrt(self.weights), 2) / scale
        block = np.stack([-np.eye(dim), np.eye(dim)], axis=0)                  # (2, dim, dim)
        G = (self.w[:, None, None, None] * block[None]).transpose(0, 2, 1, 3)
        self.G = G.reshape(-1, 2, dim)                                      # (2q dim, 2, dim)

    def evaluate(self, X: np.ndarray, grad: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        targets = np.concatenate([self.frame_edges[:, 0], self.frame_edges[:, 1]])
        d = X[self.pairs[:, 1]] - X[self.pairs[:, 0]] - targets
        return (self.w[:, None] * d).ravel(), (self.G if grad else None)


def square_sum(r: np.ndarray) -> float:
    """``r . r`` of a residual vector, without BLAS: numpy's ``dot`` hands long vectors to
    a multithreaded BLAS, whose threads cost ~20 ms per call on a loaded machine (measured
    at load 7-10 on 2 cores: 8 dot products of 30K entries took 170 ms, ``einsum`` 0.2 ms;
    ``python -m bench.blas_threads``)."""
    return float(np.einsum("i,i->", r, r))
