"""The rigid motions that leave the refinement's energy unchanged, and a step without them.

Lengths, dihedral angles and signed areas do not change under a rigid motion, so where no
handle holds a connected component (no fixed vertex, no soft position, no orientation
handle in it) the Gauss-Newton matrix ``J^T J`` of :mod:`solver.refine.normal_equations` is
singular along that component's infinitesimal rigid motions (3 translations and 3
rotations; 2 and 1 in the plane). Levenberg-Marquardt's damping makes it definite, and at
the point where it was built the gradient has no component along those motions, so the
fresh Gauss-Newton step is fine. A factor used again after the positions moved (a frozen
Gauss-Newton or an L-BFGS step of :mod:`solver.refine`) is not: the new gradient has a small
component along the *old* point's rotations, which the factor multiplies by the inverse of
the damping (1e9), and the step becomes a huge linearized rotation, which stretches every
edge. Such steps were refused at every step length (rocker-arm, angles x 0.8: one
factorization of three was spent on it; with 30 needle edges: two of seven).

:class:`RigidMotions` removes from a step its components along the infinitesimal rigid
motions of the positions its factor was built at: an orthogonal projection per component,
with per-component sums (translations: the mean; rotations: the angular momentum against
the inertia tensor). The motions removed change ``E`` only to second order.
"""

from __future__ import annotations

import numpy as np

from .topology import MeshTopology


class RigidMotions:
    """Projection of steps off the free rigid motions of the unheld components.

    Args:
        topology: the mesh connectivity (its vertex components).
        free: (n,) bool the vertices that move (the unknowns, vertex-major).
        held: (n,) bool vertices that a handle holds (fixed, soft or in an orientation
            handle's face): their components have no free rigid motion.
        dim: 3, or 2 for a planar fit.

    Attributes:
        active: whether some component has free rigid motions (else :meth:`at` gives a
            projection that changes nothing).
    """

    def __init__(self, topology: MeshTopology, free: np.ndarray, held: np.ndarray,
                 dim: int) -> None:
        component = topology.vertex_component
        n_components = int(component.max()) + 1 if len(component) else 0
        held_components = np.zeros(n_components, dtype=bool)
        held_components[component[held]] = True
        free_component = component[free]
        gauged = ~held_components[free_component]
        self.dim = dim
        self.active = bool(gauged.any())
        # Rows (among the free vertices) whose components are projected, and a dense
        # numbering of those components.
        self._rows = np.flatnonzero(gauged)
        _, self._label = np.unique(free_component[self._rows], return_inverse=True)
        self._count = int(self._label.max()) + 1 if len(self._label) else 0
        # Every free vertex projected: the step's rows are used where they are (no gather
        # and scatter of the rows, the common case of one unheld mesh).
        self._every_row = len(self._rows) == len(free_component)

    def at(self, X_free: np.ndarray) -> RigidProjection:
        """The projection for a factor built at the free positions ``X_free`` (n_free, dim)."""
        return RigidProjection(self, X_free)


class RigidProjection:
    """Removes the infinitesimal rigid motions of fixed positions from vectors.

    Built by :meth:`RigidMotions.at`; :meth:`__call__` takes a step (n_free * dim,) float64,
    vertex-major, and returns it without its components along the translations and
    rotations (about each component's centroid) of those positions: the Euclidean
    orthogonal projection, since translations and rotations about the centroid are
    orthogonal.
    """

    def __init__(self, motions: RigidMotions, X_free: np.ndarray) -> None:
        self.motions = motions
        if not motions.active:
            return
        label, count = motions._label, motions._count
        X = X_free[motions._rows]
        self._size = np.bincount(label, minlength=count).astype(np.float64)
        centroid = _sums(X, label, count) / self._size[:, None]
        self._r = X - centroid[label]                                   # (k, dim)
        r = self._r
        if motions.dim == 3:
            # Inertia tensor per component: sum |r|^2 I - r r^T; its inverse (pseudo-inverse
            # for collinear or single vertices, whose rotations about the line are not
            # motions at all).
            outer = _sums((r[:, :, None] * r[:, None, :]).reshape(len(r), 9), label,
                          count).reshape(count, 3, 3)
            trace = np.trace(outer, axis1=1, axis2=2)
            inertia = trace[:, None, None] * np.eye(3) - outer
            self._inverse_inertia = np.linalg.pinv(inertia, hermitian=True)
        else:
            second = np.bincount(label, np.einsum("ij,ij->i", r, r), minlength=count)
            self._inverse_inertia = np.where(second > 0, 1.0 / np.where(second > 0, second,
                                                                         1.0), 0.0)

    def __call__(self, step: np.ndarray) -> np.ndarray:
        motions = self.motions
        if not motions.active:
            return step
        label, count, dim = motions._label, motions._count, motions.dim
        out = step.reshape(-1, dim).copy()
        s = out if motions._every_row else out[motions._rows]
        s -= _per_row(_sums(s, label, count) / self._size[:, None], label, count)  # translations
        r = self._r
        if dim == 3:
            momentum = _sums(_cross(r, s), label, count)                  # (count, 3)
            omega = np.einsum("cij,cj->ci", self._inverse_inertia, momentum)
            s -= _cross(_per_row(omega, label, count), r)
        else:
            momentum = _sums((r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0])[:, None], label,
                             count)[:, 0]
            omega = _per_row(self._inverse_inertia * momentum, label, count)
            s[:, 0] += omega * r[:, 1]
            s[:, 1] -= omega * r[:, 0]
        if not motions._every_row:
            out[motions._rows] = s
        return out.reshape(step.shape)


def _sums(values: np.ndarray, label: np.ndarray, count: int) -> np.ndarray:
    """Column sums (count, c) of ``values`` (k, c) per ``label`` (k,)."""
    if count == 1:
        return values.sum(axis=0, keepdims=True)
    return np.stack([np.bincount(label, values[:, c], minlength=count)
                     for c in range(values.shape[1])], axis=1)


def _per_row(values: np.ndarray, label: np.ndarray, count: int) -> np.ndarray:
    """``values[label]`` (k, ...) from per-component ``values`` (count, ...); with one
    component its row, broadcast."""
    return values[:1] if count == 1 else values[label]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products (k, 3) of (k, 3) or (1, 3) arrays (``numpy.cross`` without
    its axis handling)."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=1)
