"""The refinement's energy with its exact Hessian and its mixed derivatives in the targets.

:mod:`solver.refine` minimizes (dim 3, uniform edge weights, the setting of
:func:`solver.reconstruct`)::

    E(x) = 1/2 sum_e (l_e(x) / L_e - 1)^2 + beta/2 sum_e wrap(theta_e(x) - Theta_e)^2
         + 1/2 sum_t |x_c - (1 - t_t) x_a - t_t x_b|^2 / L_ab^2
         + 1/2 sum_v w_v |x_v - p_v|^2 / s^2 + 1/2 sum_t w_t sum_c |x_tc - x_t0 - E_tc|^2 / s^2

with ``s`` the mean target length; the second sum leaves out the edges of cap faces, whose
apex the third holds on their base (:func:`solver.refine.form_energy.cap_faces`, where beta > 0).
Levenberg-Marquardt there only needs ``J^T J``; implicit
differentiation of its optimum needs the stationarity condition ``grad E(x*; targets) = 0``
differentiated exactly: the Hessian ``H = J^T J + sum_r r_r Hess(r_r)`` (the second term is
what distinguishes the optimum of forms that no surface has from an exact fit) and the
mixed derivatives ``d grad E / d targets``. This module evaluates ``E``, its gradient, the
exact Hessian (assembled as a sparse matrix in 3x3 vertex blocks) and ``lambda^T d grad E /
d targets`` for a batch of vectors ``lambda``.

The dihedral angle's Hessian is the directional derivative of the Bridson et al. gradient
of :func:`solver.mesh.embedding_geometry.hinge_angles`, written out in forward mode (12 directions
per hinge, one vectorized pass each). Everything here is a pure function of the positions and the
targets: a test checks that :meth:`RefinedEnergy.energy` equals
:meth:`solver.refine.Refiner.energy`, so a change of the refinement's energy fails it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..mesh.embedding_geometry import hinge_angles, hinges
from ..mesh.metrics import wrap_angle
from .form_energy import DEGENERATE, FormTargets, Handles, cap_faces


@dataclass
class MixedCotangents:
    """``lambda^T d(grad E)/d(target)`` for B vectors lambda (each target's shape, B first).

    Attributes:
        lengths: (B, E). angles: (B, E). soft_positions: (B, p, 3).
        frame_edges: (B, q, 2, 3). scale: (B,) (the mean target length ``s``).
    """

    lengths: np.ndarray
    angles: np.ndarray
    soft_positions: np.ndarray
    frame_edges: np.ndarray
    scale: np.ndarray


def hinge_gradient_derivative(X: np.ndarray, hinge: np.ndarray, V: np.ndarray,
                              floor: float = 0.0) -> np.ndarray:
    """Directional derivative (k, 4, 3) of the dihedral gradients of
    :func:`solver.mesh.embedding_geometry.hinge_angles` (k hinges [i, j, a, b] of ``X`` (n, 3))
    along the
    displacements ``V`` (k, 4, 3) of the hinges' vertices: ``Hess(theta) V`` per hinge.
    (Faces below ``floor`` have a clamped ``|N|^2`` whose derivative is taken as 0.)"""
    xi, xj, xa, xb = (X[hinge[:, c]] for c in range(4))
    vi, vj, va, vb = (V[:, c] for c in range(4))
    dot = lambda p, q: np.einsum("ij,ij->i", p, q)  # noqa: E731
    e, de = xj - xi, vj - vi
    elen = np.sqrt(dot(e, e))
    elen = np.where(elen > 0, elen, 1.0)
    delen = dot(e, de) / elen
    n_left = np.cross(e, xa - xi)
    n_right = np.cross(xi - xj, xb - xj)
    dn_left = np.cross(de, xa - xi) + np.cross(e, va - vi)
    dn_right = np.cross(vi - vj, xb - xj) + np.cross(xi - xj, vb - vj)
    q_left, q_right = dot(n_left, n_left), dot(n_right, n_right)
    dq_left = np.where(q_left > floor, 2.0 * dot(n_left, dn_left), 0.0)
    dq_right = np.where(q_right > floor, 2.0 * dot(n_right, dn_right), 0.0)
    q_left, q_right = np.maximum(q_left, floor), np.maximum(q_right, floor)
    u_left, u_right = n_left / q_left[:, None], n_right / q_right[:, None]
    du_left = dn_left / q_left[:, None] - n_left * (dq_left / q_left**2)[:, None]
    du_right = dn_right / q_right[:, None] - n_right * (dq_right / q_right**2)[:, None]

    def scaled_dot(p, q, dp, dq):  # (p . q) / |e| and its derivative
        value = dot(p, q) / elen
        return value[:, None], ((dot(dp, q) + dot(p, dq)) / elen - value * delen / elen)[:, None]

    s_aj, ds_aj = scaled_dot(xa - xj, e, va - vj, de)
    s_bj, ds_bj = scaled_dot(xb - xj, e, vb - vj, de)
    s_ai, ds_ai = scaled_dot(xa - xi, e, va - vi, de)
    s_bi, ds_bi = scaled_dot(xb - xi, e, vb - vi, de)
    d_a = -(delen[:, None] * u_left + elen[:, None] * du_left)
    d_b = -(delen[:, None] * u_right + elen[:, None] * du_right)
    d_i = -(ds_aj * u_left + s_aj * du_left + ds_bj * u_right + s_bj * du_right)
    d_j = ds_ai * u_left + s_ai * du_left + ds_bi * u_right + s_bi * du_right
    return np.stack([d_i, d_j, d_a, d_b], axis=1)


class _BlockPattern:
    """Symmetric 3x3-block sparsity pattern of vertex pairs, accumulated by scatter."""

    def __init__(self, n: int, pairs: list[np.ndarray]) -> None:
        diag = np.arange(n, dtype=np.int64) * (n + 1)
        keys = [diag] + [p[:, 0] * n + p[:, 1] for p in pairs] + [p[:, 1] * n + p[:, 0]
                                                                     for p in pairs]
        self.n = n
        self.keys = np.unique(np.concatenate(keys))
        self.values = np.zeros(len(self.keys) * 9)

    def clear(self) -> None:
        self.values = np.zeros(len(self.keys) * 9)

    def add(self, a: np.ndarray, b: np.ndarray, blocks: np.ndarray) -> None:
        """Add blocks (r, 3, 3) at vertex pairs (a, b) (both (r,))."""
        where = np.searchsorted(self.keys, a * self.n + b)
        index = (where[:, None] * 9 + np.arange(9)).ravel()
        self.values += np.bincount(index, blocks.reshape(-1), minlength=len(self.values))

    def matrix(self) -> sp.csr_array:
        rows, cols = np.divmod(self.keys, self.n)
        indptr = np.searchsorted(rows, np.arange(self.n + 1))
        B = sp.bsr_array((self.values.reshape(-1, 3, 3), cols, indptr),
                         shape=(3 * self.n, 3 * self.n))
        return sp.csr_array(B.tocsr())


class RefinedEnergy:
    """``E`` of :mod:`solver.refine` for ``targets`` and ``handles`` (fixed vertices are
    ignored here: :meth:`hessian` covers every vertex, the caller selects the free ones).

    Args:
        targets: :class:`solver.refine.FormTargets` with uniform weighting.
        handles: :class:`solver.refine.Handles` (soft positions and orientation handles).
    """

    def __init__(self, targets: FormTargets, handles: Handles) -> None:
        if targets.weighting != "uniform":
            raise ValueError("derivatives of the refinement cover the uniform weighting only")
        topo = targets.topology
        self.topology = topo
        self.n = topo.n_vertices
        self.lengths = np.asarray(targets.lengths, dtype=np.float64)
        self.angles = np.asarray(targets.angles, dtype=np.float64)
        self.beta = float(targets.angle_weight)
        self.scale = float(np.mean(self.lengths))
        self.floor = DEGENERATE * self.scale**4
        self.inner, self.hinge = hinges(topo)
        # Cap faces, where the angles weigh: their edges' angles are left out.
        caps = cap_faces(topo, self.lengths)
        chosen = slice(None) if self.beta > 0 else slice(0)
        kept = np.flatnonzero(~caps.is_cap_edge[self.inner])[chosen]
        self.inner, self.hinge = self.inner[kept], self.hinge[kept]
        self.cap_corners = caps.corners[chosen]
        self.cap_coefficients = caps.coefficients[chosen]
        self.cap_edges, self.cap_lengths = caps.edges[chosen], caps.lengths[chosen]
        self.soft_vertices = np.asarray(handles.soft_vertices, dtype=np.int64)
        self.soft_positions = np.asarray(handles.soft_positions, dtype=np.float64).reshape(-1, 3)
        self.soft_weights = np.asarray(handles.soft_weights, dtype=np.float64)
        F = topo.faces[np.asarray(handles.frame_faces, dtype=np.int64)]
        self.frame_pairs = np.stack([F[:, [0, 1]], F[:, [0, 2]]], axis=1)   # (q, 2, 2)
        self.frame_edges = np.asarray(handles.frame_edges, dtype=np.float64).reshape(-1, 2, 3)
        self.frame_weights = np.asarray(handles.frame_weights, dtype=np.float64)
        self._pattern: _BlockPattern | None = None

    # -- residual pieces

    def _lengths(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        edges = self.topology.edges
        d = X[edges[:, 1]] - X[edges[:, 0]]
        length = np.sqrt(np.einsum("ij,ij->i", d, d))
        unit = d / np.where(length > 0, length, 1.0)[:, None]
        return length, unit, length / self.lengths - 1.0

    def _frame_residuals(self, X: np.ndarray) -> np.ndarray:
        """(q, 2, 3) ``x_tc - x_t0 - E_tc``."""
        p = self.frame_pairs
        return X[p[:, :, 1]] - X[p[:, :, 0]] - self.frame_edges

    def _cap_residuals(self, X: np.ndarray) -> np.ndarray:
        """(k, 3) ``(x_c - (1 - t) x_a - t x_b) / L_ab`` of the cap faces."""
        return np.einsum("kc,kcd->kd", self.cap_coefficients, X[self.cap_corners])

    def energy(self, X: np.ndarray) -> float:
        """E(X) for positions (n, 3)."""
        _, _, r_len = self._lengths(X)
        theta, _ = hinge_angles(X, self.hinge, self.floor, gradients=False)
        r_ang = wrap_angle(theta - self.angles[self.inner])
        soft = X[self.soft_vertices] - self.soft_positions
        frame = self._frame_residuals(X)
        cap = self._cap_residuals(X)
        s2 = self.scale**2
        return 0.5 * float(r_len @ r_len + self.beta * (r_ang @ r_ang) + np.sum(cap * cap)
                           + np.einsum("v,vk,vk->", self.soft_weights, soft, soft) / s2
                           + np.einsum("q,qck,qck->", self.frame_weights, frame, frame) / s2)

    def gradient(self, X: np.ndarray) -> np.ndarray:
        """grad E (n, 3)."""
        n, s2 = self.n, self.scale**2
        grad = np.zeros((n, 3))
        edges = self.topology.edges
        _length, unit, r_len = self._lengths(X)
        c = (r_len / self.lengths)[:, None] * unit
        self._scatter(grad, edges[:, 1], c)
        self._scatter(grad, edges[:, 0], -c)
        theta, G = hinge_angles(X, self.hinge, self.floor)
        r_ang = wrap_angle(theta - self.angles[self.inner])
        for slot in range(4):
            self._scatter(grad, self.hinge[:, slot], self.beta * r_ang[:, None] * G[:, slot])
        cap = self._cap_residuals(X)
        for corner in range(3):
            self._scatter(grad, self.cap_corners[:, corner],
                          self.cap_coefficients[:, corner, None] * cap)
        soft = self.soft_weights[:, None] * (X[self.soft_vertices] - self.soft_positions) / s2
        self._scatter(grad, self.soft_vertices, soft)
        frame = self.frame_weights[:, None, None] * self._frame_residuals(X) / s2
        self._scatter(grad, self.frame_pairs[:, :, 1].ravel(), frame.reshape(-1, 3))
        self._scatter(grad, self.frame_pairs[:, :, 0].ravel(), -frame.reshape(-1, 3))
        return grad

    @staticmethod
    def _scatter(out: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
        for k in range(out.shape[1]):
            out[:, k] += np.bincount(index, values[:, k], minlength=len(out))

    def hessian(self, X: np.ndarray, exact: bool = True) -> sp.csr_array:
        """The exact Hessian of E (3n, 3n), symmetric CSR, row ``3 v + k`` = coordinate k of
        vertex v: ``J^T J`` plus the residual-weighted second derivatives of every residual
        (lengths: ``r (I - u u^T) / (l L)``; dihedral angles: ``beta r Hess(theta)``).
        ``exact=False``: the Gauss-Newton matrix ``J^T J`` alone (for comparisons)."""
        edges, hinge = self.topology.edges, self.hinge
        if self._pattern is None:   # vertex pairs sharing an edge or a hinge's two tips
            self._pattern = _BlockPattern(self.n, [edges, hinge[:, 2:4]])
        pattern = self._pattern
        pattern.clear()
        eye = np.eye(3)
        length, unit, r_len = self._lengths(X)
        if not exact:
            r_len = np.zeros_like(r_len)
        L = self.lengths
        outer = unit[:, :, None] * unit[:, None, :]
        block = (outer / L[:, None, None] ** 2
                 + (r_len / (length * L))[:, None, None] * (eye - outer))
        i, j = edges[:, 0], edges[:, 1]
        pattern.add(i, i, block)
        pattern.add(j, j, block)
        pattern.add(i, j, -block)
        pattern.add(j, i, -block)
        if len(hinge):
            theta, G = hinge_angles(X, hinge, self.floor)
            r_ang = wrap_angle(theta - self.angles[self.inner]) * float(exact)
            k = len(hinge)
            columns = np.empty((k, 4, 3, 4, 3))   # [hinge, slot_row, coord_row, slot, coord]
            for slot in range(4):
                for coord in range(3):
                    V = np.zeros((k, 4, 3))
                    V[:, slot, coord] = 1.0
                    dG = hinge_gradient_derivative(X, hinge, V, self.floor)
                    columns[:, :, :, slot, coord] = self.beta * (
                        G * G[:, slot, coord][:, None, None] + r_ang[:, None, None] * dG)
            for a in range(4):
                for b in range(4):
                    pattern.add(hinge[:, a], hinge[:, b], columns[:, a, :, b, :])
        for p in range(3):   # cap faces: constant blocks c_p c_q I
            for q in range(3):
                weight = self.cap_coefficients[:, p] * self.cap_coefficients[:, q]
                pattern.add(self.cap_corners[:, p], self.cap_corners[:, q],
                            weight[:, None, None] * eye)
        s2 = self.scale**2
        if len(self.soft_vertices):
            pattern.add(self.soft_vertices, self.soft_vertices,
                        (self.soft_weights / s2)[:, None, None] * eye)
        if len(self.frame_weights):
            w = np.repeat(self.frame_weights / s2, 2)[:, None, None] * eye
            t0 = self.frame_pairs[:, :, 0].ravel()
            tc = self.frame_pairs[:, :, 1].ravel()
            pattern.add(t0, t0, w)
            pattern.add(tc, tc, w)
            pattern.add(t0, tc, -w)
            pattern.add(tc, t0, -w)
        return pattern.matrix()

    def hessian_vector(self, X: np.ndarray, V: np.ndarray) -> np.ndarray:
        """``H V`` (n, 3) without assembling H (for checks and iterative solvers)."""
        n, s2 = self.n, self.scale**2
        out = np.zeros((n, 3))
        edges = self.topology.edges
        length, unit, r_len = self._lengths(X)
        dv = V[edges[:, 1]] - V[edges[:, 0]]
        along = np.einsum("ij,ij->i", unit, dv)
        c = (along / self.lengths**2)[:, None] * unit + (r_len / (length * self.lengths))[
            :, None] * (dv - along[:, None] * unit)
        self._scatter(out, edges[:, 1], c)
        self._scatter(out, edges[:, 0], -c)
        if len(self.hinge):
            theta, G = hinge_angles(X, self.hinge, self.floor)
            r_ang = wrap_angle(theta - self.angles[self.inner])
            Vh = V[self.hinge]
            dG = hinge_gradient_derivative(X, self.hinge, Vh, self.floor)
            gv = np.einsum("kcd,kcd->k", G, Vh)
            contrib = self.beta * (G * gv[:, None, None] + r_ang[:, None, None] * dG)
            for slot in range(4):
                self._scatter(out, self.hinge[:, slot], contrib[:, slot])
        cap = self._cap_residuals(V)
        for corner in range(3):
            self._scatter(out, self.cap_corners[:, corner],
                          self.cap_coefficients[:, corner, None] * cap)
        self._scatter(out, self.soft_vertices,
                      (self.soft_weights / s2)[:, None] * V[self.soft_vertices])
        p = self.frame_pairs
        d = (self.frame_weights / s2)[:, None, None] * (V[p[:, :, 1]] - V[p[:, :, 0]])
        self._scatter(out, p[:, :, 1].ravel(), d.reshape(-1, 3))
        self._scatter(out, p[:, :, 0].ravel(), -d.reshape(-1, 3))
        return out

    def mixed_vjp(self, X: np.ndarray, lam: np.ndarray) -> MixedCotangents:
        """``lambda^T d(grad E)/d(target)`` for ``lam`` (B, n, 3), holding X fixed."""
        edges = self.topology.edges
        s, s3 = self.scale, self.scale**3
        length, unit, _ = self._lengths(X)
        L = self.lengths
        dl = lam[:, edges[:, 1]] - lam[:, edges[:, 0]]                       # (B, E, 3)
        lengths = -((2.0 * length - L) / L**3) * np.einsum("bek,ek->be", dl, unit)
        angles = np.zeros((len(lam), len(L)))
        if len(self.hinge):
            _, G = hinge_angles(X, self.hinge, self.floor)
            angles[:, self.inner] = -self.beta * np.einsum("bhck,hck->bh",
                                                           lam[:, self.hinge], G)
        self._cap_mixed(X, lam, lengths)
        soft_res = X[self.soft_vertices] - self.soft_positions
        lam_soft = lam[:, self.soft_vertices]
        soft_positions = -(self.soft_weights / s**2)[None, :, None] * lam_soft
        scale = -2.0 / s3 * np.einsum("v,bvk,vk->b", self.soft_weights, lam_soft, soft_res)
        p = self.frame_pairs
        frame_res = self._frame_residuals(X)
        lam_frame = lam[:, p[:, :, 1]] - lam[:, p[:, :, 0]]                    # (B, q, 2, 3)
        frame_edges = -(self.frame_weights / s**2)[None, :, None, None] * lam_frame
        scale = scale - 2.0 / s3 * np.einsum("q,bqck,qck->b", self.frame_weights, lam_frame,
                                             frame_res)
        return MixedCotangents(lengths, angles, soft_positions, frame_edges, scale)

    def _cap_mixed(self, X: np.ndarray, lam: np.ndarray, lengths: np.ndarray) -> None:
        """Add the cap faces' ``lambda^T d(grad E)/d(lengths)`` to ``lengths`` (B, E).

        With ``k = (t - 1, -t, 1) / L_ab`` (:attr:`CapFaces.coefficients`), a cap's
        residual is ``r = sum_p k_p x_p`` and its gradient ``k_p r`` at corner p, so ``lambda
        . grad = r . m`` with ``m = sum_p k_p lambda_p``. Its derivative in ``t`` (``dk/dt =
        (1, -1, 0) / L_ab``) is ``((x_a - x_b) . m + r . (lambda_a - lambda_b)) / L_ab``, in
        ``L_ab`` through the common factor ``1 / L_ab`` of both ``-2 r . m / L_ab``; and
        ``t = 1/2 + (L_ca^2 - L_bc^2) / (2 L_ab^2)``."""
        if not len(self.cap_corners):
            return
        L = self.cap_lengths
        a, b = self.cap_corners[:, 0], self.cap_corners[:, 1]
        r = self._cap_residuals(X)                                             # d / L_ab
        m = np.einsum("kc,bkcd->bkd", self.cap_coefficients, lam[:, self.cap_corners])
        base2 = L[:, 0] ** 2
        along = (np.einsum("kd,bkd->bk", X[a] - X[b], m)                         # d/dt
                 + np.einsum("kd,bkd->bk", r, lam[:, a] - lam[:, b])) / L[:, 0]
        dt = np.stack([-(L[:, 2] ** 2 - L[:, 1] ** 2) / L[:, 0] ** 3,           # d t / d L_ab
                       -L[:, 1] / base2, L[:, 2] / base2], axis=1)             # L_bc, L_ca
        values = along[:, :, None] * dt[None]                                   # (B, k, 3)
        values[:, :, 0] -= 2.0 * np.einsum("kd,bkd->bk", r, m) / L[:, 0]
        np.add.at(lengths, (slice(None), self.cap_edges.ravel()),
                  values.reshape(len(lam), -1))
