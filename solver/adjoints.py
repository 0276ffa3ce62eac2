"""The adjoints behind :func:`solver.differentiable.reconstruct_vjp`.

:class:`LinearAdjoint` differentiates the linear answer of Eq. (5) by the adjoint method
(one back-substitution with the factorized ``K`` per cotangent); :class:`RefinedAdjoint`
differentiates the refinement's optimum implicitly with the exact Hessian, after polishing
it with Newton steps, and its rigid placement. Both return :class:`FormCotangents`. The
module docstring of :mod:`solver.differentiable` says which map each one differentiates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from .immersion import ImmersionProblem
from .linalg import Factorization, SingularSystemError, factorize
from .linear.constraints import Constraints
from .linear.system import ConstrainedSystem, LinearConstraints
from .mesh.form_derivatives import face_lengths_vjp, layout_terms_vjp, layouts_vjp
from .mesh.frames import face_edge_lengths, layout_frames
from .mesh.rotations import nearest_rotation
from .reconstruct import Reconstruction
from .refine.form_energy import FormTargets
from .refine.refined_energy import RefinedEnergy

POLISH_TOLERANCE = 1e-9
"""Newton polishing stops after a step below this fraction of the mean edge length."""
POLISH_ITERATIONS = 30
"""Most Newton steps polishing takes."""
REUSE_TOLERANCE = 1e-6
"""A polishing step below this fraction of the mean edge length is taken without
refactorizing the Hessian at its end point (the factorized one is O(step) away)."""


@dataclass
class FormCotangents:
    """Cotangents of the inputs of :func:`solver.reconstruct` (batch axis B first when the
    cotangent had one).

    Attributes:
        lengths: (E,) float64.
        angles: (E,) float64.
        positions: (p, 3) float64 of ``constraints.positions`` (hard and soft), in their
            order.
        frames: (q, 3, 3) float64 of ``constraints.frames``.
    """

    lengths: np.ndarray
    angles: np.ndarray
    positions: np.ndarray
    frames: np.ndarray


# ------------------------------------------------------------------- the linear answer


class LinearAdjoint:
    """Adjoint of the constrained system of Eq. (5): ``(K + S) u = rhs`` on the free
    unknowns, ``u = h`` on the hard ones (:class:`solver.linear.system.ConstrainedSystem`).

    Args:
        problem: the reconstruction's system.
        user: the validated constraints.
        lengths: (E,) float64 edge lengths in the caller's units.
        backend: sparse factorization backend.
        scale_from_mean: the length scale is the mean edge length (so it depends on the
            lengths too).
    """

    def __init__(self, problem: ImmersionProblem, user: Constraints, lengths: np.ndarray,
                 backend: str, scale_from_mean: bool) -> None:
        self.problem, self.user, self.lengths = problem, user, lengths
        self.scale_from_mean = scale_from_mean
        linear = problem.linear_constraints(user)
        touched = problem.constrained_components(user)
        anchor, _ = problem.anchors(~touched)
        self.linear: LinearConstraints = linear.extended(anchor)
        # Built as reconstruct built its last system (K handed over, the constrained matrix
        # made in place from it): the same matrix to the bit, so a system that is nearly
        # singular along what a tiny soft weight fixes still gives reconstruct's answer.
        self.system: ConstrainedSystem = problem.system(self.linear, backend, release=True)
        self.u = self.system.solve(self.linear.hard_values, self.linear.soft_values)
        hard_pos = np.isinf(user.position_weights)
        hard_frm = np.isinf(user.frame_weights)
        self.hard_pos, self.hard_frm = hard_pos, hard_frm

    def check(self, vertices: np.ndarray) -> None:
        """Refuse to differentiate a system whose answer is not ``vertices`` (n, 3)."""
        mine, _ = self.problem.unknowns_to_geometry(self.u.copy(), self.user)
        size = max(float(np.abs(vertices).max(initial=0.0)), self.problem.length_scale)
        if not np.abs(mine - vertices).max(initial=0.0) <= 1e-6 * size:
            raise RuntimeError("internal: the differentiated linear system does not "
                               "reproduce reconstruct's answer")

    def vjp(self, g: np.ndarray) -> FormCotangents:
        """Cotangents of the inputs for ``g`` (B, n, 3) float64."""
        problem, system, linear = self.problem, self.system, self.linear
        topo, terms = problem.topology, problem.terms
        n, m, B = topo.n_vertices, topo.n_faces, len(g)
        N = problem.n_unknowns
        s = problem.length_scale
        u = self.u
        g_u = np.zeros((B, N, 3))
        g_u[:, :n] = s * g
        scale_bar = np.einsum("bvk,vk->b", g, u[:n])            # x = s u
        rhs = g_u.copy()
        rhs[:, linear.hard_columns] = 0.0
        lam = system.factor.solve(rhs.transpose(1, 0, 2).reshape(N, 3 * B))
        lam = lam.reshape(N, B, 3)                              # (N, B, 3)
        lam[linear.hard_columns] = 0.0
        # d(lambda^T K u) / d(forms), K = A^T W A: residuals of u and lambda, row by row.
        A, w = problem.A, problem.row_weights
        H = 3 * m
        r_u = A @ u                                             # (rows, 3)
        r_l = (A @ lam.reshape(N, 3 * B)).reshape(-1, B, 3)     # (rows, B, 3)
        F_u = u[n:].reshape(m, 3, 3)                            # [t, c, k] = f_t[k, c]
        F_l = lam[n:].reshape(m, 3, B, 3).transpose(2, 0, 1, 3)  # (B, m, 3, 3)
        w_e = w[:H].reshape(m, 3)
        ru_e = r_u[:H].reshape(m, 3, 3)                         # [t, h, k]
        rl_e = r_l[:H].reshape(m, 3, B, 3).transpose(2, 0, 1, 3)
        # grad = -d(lambda^T K u)/d(forms) (du = -K^-1 dK u); dA u = -f_T da, -f_L dR.
        coefficients_bar = w_e[None, :, :, None] * (
            np.einsum("btck,thk->bthc", F_l[:, :, :2], ru_e)
            + np.einsum("tck,bthk->bthc", F_u[:, :2], rl_e))
        inner = terms.interior_edges
        left = topo.edge_faces[inner, 0]
        q = len(inner)
        w_f = w[H:].reshape(q, 3)[:, 0]
        ru_f = r_u[H:].reshape(q, 3, 3)                         # [q, c, k]
        rl_f = r_l[H:].reshape(q, 3, B, 3).transpose(2, 0, 1, 3)
        rotations_bar = w_f[None, :, None, None] * (
            np.einsum("bqdk,qck->bqdc", F_l[:, left], ru_f)
            + np.einsum("qdk,bqck->bqdc", F_u[left], rl_f))
        normalized = self.lengths / s
        face_lengths = face_edge_lengths(topo, normalized)
        lengths_bar, angles_bar = layout_terms_vjp(
            topo, face_lengths, terms.layouts, terms.coefficients, terms.transition,
            terms.rotations, coefficients_bar, rotations_bar)
        # Constraint targets: u_hard = h, soft pulls towards v (both in units of s).
        lam_b = lam.transpose(1, 0, 2)                          # (B, N, 3)
        coupling = np.stack([system.K_hard_rows @ lam_b[b] for b in range(B)])
        hard_bar = g_u[:, linear.hard_columns] - coupling       # (B, h, 3)
        soft_bar = linear.soft_weights[None, :, None] * lam_b[:, linear.soft_columns]
        user = self.user
        n_ph, n_fh = int(self.hard_pos.sum()), int(self.hard_frm.sum())
        n_ps, n_fs = int((~self.hard_pos).sum()), int((~self.hard_frm).sum())
        positions = np.zeros((B, len(user.position_vertices), 3))
        frames = np.zeros((B, len(user.frame_faces), 3, 3))
        h_pos, v_pos = hard_bar[:, :n_ph], soft_bar[:, :n_ps]
        positions[:, self.hard_pos] = h_pos / s
        positions[:, ~self.hard_pos] = v_pos / s
        scale_bar -= (np.einsum("bpk,pk->b", h_pos, linear.hard_values[:n_ph])
                      + np.einsum("bpk,pk->b", v_pos, linear.soft_values[:n_ps])) / s
        # Frame rows: value (t, c) holds f_t[k, c] in column k.
        frames[:, self.hard_frm] = hard_bar[:, n_ph:n_ph + 3 * n_fh].reshape(
            B, n_fh, 3, 3).transpose(0, 1, 3, 2)
        frames[:, ~self.hard_frm] = soft_bar[:, n_ps:n_ps + 3 * n_fs].reshape(
            B, n_fs, 3, 3).transpose(0, 1, 3, 2)
        # Normalized lengths L / s.
        if self.scale_from_mean:
            scale_bar -= np.einsum("be,e->b", lengths_bar, normalized) / s
            lengths_out = lengths_bar / s + scale_bar[:, None] / len(normalized)
        else:
            lengths_out = lengths_bar / s
        return FormCotangents(lengths_out, angles_bar, positions, frames)


# ------------------------------------------------------------------ the refined answer


class RefinedAdjoint:
    """Implicit differentiation of the refinement's optimum and of its placement.

    Args:
        problem: the reconstruction's system.
        user: the validated constraints.
        L: (E,) float64 edge lengths.
        A: (E,) float64 dihedral angles.
        result: the refined reconstruction.
        angle_weight: the refinement's weight of the angle residuals.
        backend: sparse factorization backend.
        polish: take Newton steps to the optimum first.

    Attributes:
        vertices: (n, 3) float64 the (polished) optimum.
        report: factorizations, polishing steps and how far they moved.
    """

    def __init__(self, problem: ImmersionProblem, user: Constraints, L: np.ndarray,
                 A: np.ndarray, result: Reconstruction, angle_weight: float, backend: str,
                 polish: bool) -> None:
        topo = problem.topology
        self.problem, self.user, self.L, self.backend = problem, user, L, backend
        self.anchored = result.report.get("anchored_components", [])
        self.handles = problem.refinement_handles(user)
        self.energy = RefinedEnergy(FormTargets(topo, L, A, angle_weight=angle_weight),
                                    self.handles)
        self.fixed = np.asarray(self.handles.fixed, dtype=np.int64)
        free = topo.is_referenced.copy()
        free[self.fixed] = False
        self.free = free
        self.free_dofs = (np.flatnonzero(free)[:, None] * 3 + np.arange(3)).ravel()
        self.fixed_dofs = (self.fixed[:, None] * 3 + np.arange(3)).ravel()
        X = np.array(result.vertices, dtype=np.float64)
        self.report: dict[str, Any] = {"factorizations": 0, "polish_steps": 0,
                                       "polish_moved": 0.0}
        scale = self.energy.scale
        start = X.copy()
        damping = 0.0   # Levenberg-Marquardt damping of a polishing step, relative
        for _ in range(POLISH_ITERATIONS + 1):
            self._factor_at(X, damping)
            gradient = self.energy.gradient(X).ravel()[self.free_dofs]
            step = -self._solve(self._project(gradient[None]))[0]
            size = float(np.abs(step).max(initial=0.0)) / scale
            if not polish or (damping == 0.0 and size <= POLISH_TOLERANCE) or \
                    self.report["polish_steps"] == POLISH_ITERATIONS:
                break
            moved = self._line_search(X, step) if gradient @ step < 0 else None
            if moved is None:   # far from the optimum, H indefinite: damp
                damping = max(1e-8, 10.0 * damping)
                continue
            X = moved
            self.report["polish_steps"] += 1
            if damping == 0.0 and size <= REUSE_TOLERANCE:
                # Newton from this close: the next step would be ~size^2, and the Hessian
                # here differs from the factorized one by O(size) relative, below the
                # derivative's own accuracy target: keep the factorization.
                self.X = X
                size = 0.0
                break
            damping = 0.1 * damping if damping > 1e-8 else 0.0
        if damping:      # the derivative needs the undamped Hessian
            self._factor_at(X)
        self.report["polish_converged"] = bool(size <= POLISH_TOLERANCE)
        self.report["last_step"] = size
        self.report["polish_moved"] = float(np.abs(X - start).max(initial=0.0)) / scale
        gradient = self._project(self.energy.gradient(X).ravel()[self.free_dofs][None])
        self.report["gradient_norm"] = float(np.abs(gradient).max(initial=0.0))
        self.vertices = X

    # -- the exact Hessian on the free coordinates, gauge pinned

    def _factor_at(self, X: np.ndarray, damping: float = 0.0) -> None:
        self.X = X
        H = self.energy.hessian(X)
        H_ff = H[self.free_dofs][:, self.free_dofs]
        if damping:
            diagonal = H_ff.diagonal()
            H_ff = H_ff + sp.diags(damping * np.maximum(diagonal, 1e-9 * diagonal.mean()))
        self.H_fixed_free = H[self.fixed_dofs][:, self.free_dofs]
        self.null, pinned = self._rigid_null_space(X)
        keep = np.ones(len(self.free_dofs))
        keep[pinned] = 0.0
        D = sp.diags(keep)
        matrix = (D @ H_ff @ D + sp.diags(1.0 - keep)).tocsr()
        self.pinned = pinned
        groups = np.repeat(np.arange(len(self.free_dofs) // 3), 3)
        try:
            self.factor: Factorization = factorize(matrix, self.backend,
                                                   assume_symmetric=True, groups=groups)
        except SingularSystemError:
            # Not a strict local minimum to round-off (or a backend that wants definite
            # matrices): LU solves a nonsingular indefinite matrix correctly.
            self.factor = factorize(matrix, "superlu", assume_symmetric=True)
        self.report["factorizations"] += 1
        self.report["analysis"] = self.factor.analysis

    def _solve(self, rhs: np.ndarray) -> np.ndarray:
        """(B, n_free_dofs) -> H^-1 rhs on the pinned complement (rhs already projected)."""
        rhs = rhs.copy()
        rhs[:, self.pinned] = 0.0
        out = self.factor.solve(rhs.T).T
        out[:, self.pinned] = 0.0
        return out.reshape(rhs.shape)

    def _project(self, v: np.ndarray) -> np.ndarray:
        """Remove from v (B, n_free_dofs) its components along the free rigid motions."""
        N = self.null
        if N.shape[1] == 0:
            return v
        coefficients = np.linalg.solve(N.T @ N, N.T @ v.T)
        return v - (N @ coefficients).T

    def _rigid_null_space(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rigid motions (free coordinates x d, dense) that change no residual of E (those
        of components that no handle pins down) and d pinned free coordinates that fix them
        (pivoted QR: the coordinates the motions move most independently)."""
        topo = self.problem.topology
        h = self.handles
        scale = self.energy.scale
        comp = topo.vertex_component
        index = np.full(topo.n_vertices, -1)
        index[self.free] = np.arange(int(self.free.sum()))
        columns, pinned = [], []
        touched_vertices = np.concatenate([h.fixed, h.soft_vertices]).astype(np.int64)
        frame_components = set(topo.face_component[h.frame_faces].tolist())
        for c in range(topo.n_components):
            members = np.flatnonzero((comp == c) & topo.is_referenced)
            if not len(members):
                continue
            centre = X[members].mean(axis=0)
            held = touched_vertices[comp[touched_vertices] == c]
            gram = np.zeros((6, 6))
            for v in held:       # few: handles of one component (not a per-mesh loop)
                C = np.concatenate([np.eye(3), -_cross_matrix((X[v] - centre) / scale)], 1)
                gram += C.T @ C
            if c in frame_components:
                gram[3:, 3:] += np.eye(3)
            values, vectors = np.linalg.eigh(gram)
            null = vectors[:, values <= 1e-9 * max(1.0, float(values.max(initial=0.0)))]
            mine = members[index[members] >= 0]
            if not null.shape[1] or not len(mine):
                continue
            d = (X[mine] - centre) / scale
            fields = null[None, :3, :] + np.cross(null[3:].T[None, :, :], d[:, None, :],
                                                  axis=2).transpose(0, 2, 1)
            dofs = (index[mine][:, None] * 3 + np.arange(3)).ravel()
            block = fields.reshape(-1, null.shape[1])                # (3 |mine|, d)
            full = np.zeros((3 * len(index[self.free]), null.shape[1]))
            full[dofs] = block
            columns.append(full)
            _, pivots = scipy.linalg.qr(block.T, mode="r", pivoting=True)
            pinned.append(dofs[pivots[:null.shape[1]]])
        n_dofs = len(self.free_dofs)
        null = np.concatenate(columns, axis=1) if columns else np.zeros((n_dofs, 0))
        return null, (np.concatenate(pinned) if pinned else np.zeros(0, np.int64))

    def _line_search(self, X: np.ndarray, step: np.ndarray) -> np.ndarray | None:
        energy = self.energy.energy(X)
        for alpha in (1.0, 0.5, 0.25, 0.1, 0.01):
            trial = X.copy()
            trial[self.free] += alpha * step.reshape(-1, 3)
            if self.energy.energy(trial) <= energy + 1e-13 * max(energy, 1e-300):
                return self.problem.place_anchored(trial, self.anchored)
        return None

    # -- the VJP

    def vjp(self, g: np.ndarray) -> FormCotangents:
        """Cotangents of the inputs for ``g`` (B, n, 3) float64."""
        problem, energy, topo = self.problem, self.energy, self.problem.topology
        B, X = len(g), self.X
        g_x, layouts_bar = self._placement_vjp(g)
        g_free = self._project(g_x.reshape(B, -1)[:, self.free_dofs])
        lam_free = self._solve(g_free)
        lam = np.zeros((B, topo.n_vertices * 3))
        lam[:, self.free_dofs] = lam_free
        lam = lam.reshape(B, topo.n_vertices, 3)
        mixed = energy.mixed_vjp(X, lam)
        lengths_bar = -mixed.lengths - mixed.scale[:, None] / len(self.L)
        angles_bar = -mixed.angles
        user = self.user
        hard = np.isinf(user.position_weights)
        positions = np.zeros((B, len(user.position_vertices), 3))
        coupling = np.stack([self.H_fixed_free @ lam_free[b] for b in range(B)])
        positions[:, hard] = (g_x.reshape(B, -1)[:, self.fixed_dofs] - coupling).reshape(
            B, -1, 3)
        positions[:, ~hard] = -mixed.soft_positions
        # Orientation handles: E_t = F_t[:, :2] (planar layout edges), in input units.
        frames = np.zeros((B, len(user.frame_faces), 3, 3))
        edges_bar = -mixed.frame_edges                               # (B, q, 2, 3)
        if len(user.frame_faces):
            raw_layouts = problem.terms.layouts * problem.length_scale
            planar = raw_layouts[user.frame_faces, 1:] - raw_layouts[user.frame_faces, :1]
            frames[..., :2] = np.einsum("bqek,qec->bqkc", edges_bar, planar)
            planar_bar = np.einsum("bqek,qkc->bqec", edges_bar, user.frames[:, :, :2])
            layouts_bar[:, user.frame_faces, 1:] += planar_bar
            layouts_bar[:, user.frame_faces, 0] -= planar_bar.sum(axis=2)
        lengths_bar = lengths_bar + self._layouts_to_lengths(layouts_bar)
        return FormCotangents(lengths_bar, angles_bar, positions, frames)

    def _layouts_to_lengths(self, layouts_bar: np.ndarray) -> np.ndarray:
        problem = self.problem
        topo = problem.topology
        raw_layouts = problem.terms.layouts * problem.length_scale
        return face_lengths_vjp(topo, layouts_vjp(face_edge_lengths(topo, self.L),
                                                  raw_layouts, layouts_bar))

    def _placement_vjp(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pull ``g`` (B, n, 3) back through ``place_anchored``: ``y = R^T (x - x_a)`` on each
        anchored component, R the polar factor of the anchor face's layout frame (which
        depends on the lengths through that face's layout). Returns (g_x (B, n, 3),
        cotangent of the raw layouts (B, m, 3, 2))."""
        problem, X = self.problem, self.X
        topo = problem.topology
        B = len(g)
        g_x = g.copy()
        layouts_bar = np.zeros((B, topo.n_faces, 3, 2))
        raw_layouts = problem.terms.layouts * problem.length_scale
        for anchor in self.anchored:     # one per component (not a per-mesh loop)
            c, a, t = anchor["component"], anchor["vertex"], anchor["face"]
            members = np.flatnonzero(topo.vertex_component == c)
            F = layout_frames(X, topo.faces[[t]], raw_layouts[[t]])[0]
            R = nearest_rotation(F)
            d = X[members] - X[a]                                       # (v, 3)
            gy = g[:, members]                                          # (B, v, 3)
            g_x[:, members] = gy @ R.T                                  # R g_y
            g_x[:, a] -= (gy @ R.T).sum(axis=1)
            R_bar = np.einsum("vi,bvj->bij", d, gy)                     # sum d g^T
            F_bar = _polar_vjp(F, R, R_bar)                             # (B, 3, 3)
            b1, b2 = F[:, 0], F[:, 1]
            c_bar = F_bar[:, :, 2]
            B_bar = F_bar[:, :, :2].copy()
            B_bar[:, :, 0] += np.cross(b2[None], c_bar)
            B_bar[:, :, 1] += np.cross(c_bar, b1[None])
            corners = raw_layouts[t]
            P = np.stack([corners[1] - corners[0], corners[2] - corners[0]], axis=1)
            P_inv_T = np.linalg.inv(P).T
            Bm = F[:, :2]
            Xe_bar = B_bar @ P_inv_T                                     # (B, 3, 2)
            P_bar = -np.einsum("ki,bkj->bij", Bm, B_bar) @ P_inv_T      # -B^T B_bar P^-T
            f = topo.faces[t]
            g_x[:, f[1]] += Xe_bar[:, :, 0]
            g_x[:, f[2]] += Xe_bar[:, :, 1]
            g_x[:, f[0]] -= Xe_bar.sum(axis=2)
            layouts_bar[:, t, 1] += P_bar[:, :, 0]
            layouts_bar[:, t, 2] += P_bar[:, :, 1]
            layouts_bar[:, t, 0] -= P_bar[:, :, 0] + P_bar[:, :, 1]
        return g_x, layouts_bar


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    """[v]_x (3, 3): [v]_x w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _polar_vjp(F: np.ndarray, R: np.ndarray, R_bar: np.ndarray) -> np.ndarray:
    """Cotangent (B, 3, 3) of F (3, 3, det > 0) from that of its polar factor R = F S^-1:
    ``F_bar = R Y`` with ``Y S + S Y = R^T R_bar - R_bar^T R`` (S = R^T F)."""
    S = R.T @ F
    S = 0.5 * (S + S.T)
    sigma, Q = np.linalg.eigh(S)
    C = np.einsum("ij,bjk->bik", R.T, R_bar)
    C = C - np.swapaxes(C, 1, 2)
    Ct = np.einsum("ji,bjk,kl->bil", Q, C, Q)
    Y = np.einsum("ij,bjk,lk->bil", Q, Ct / (sigma[:, None] + sigma[None, :]), Q)
    return np.einsum("ij,bjk->bik", R, Y)
