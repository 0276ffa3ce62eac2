"""Differentiable reconstruction: vector-Jacobian products of :func:`solver.reconstruct`.

``result, vjp = reconstruct_vjp(faces, edges, lengths, angles, **keywords of reconstruct)``
returns what :func:`solver.reconstruct.reconstruct` returns and a callable: ``vjp(g)``, with
``g`` the cotangent of ``result.vertices`` ((n, 3), or (k, n, 3) for k cotangents), returns
``(grad_lengths, grad_angles)``, each (E,) or (k, E). :meth:`ReconstructionVJP.cotangents`
also gives the cotangents of the constraint targets (positions and frames). Every cotangent
reuses one factorization.

Which map is differentiated:

* ``refine=False`` -- the **linear answer** of Eq. (5) (uniform weighting, no
  orthonormalization): ``K(forms) u = rhs(targets)`` with the hard anchors of
  :func:`solver.reconstruct.reconstruct`. Adjoint method: ``K lambda = g`` (one
  back-substitution with the factorized ``K``, three columns per cotangent), then
  ``d(lambda^T K u)/d forms`` through the edge coefficients and the transition rotations
  (:mod:`solver.mesh.form_derivatives`). Its gauge is the anchor itself (each component's first
  face's first vertex at the origin, that face's frame the identity), differentiated
  exactly. The linear energy is invariant under every linear map of (x, f), so for forms
  that do not integrate another anchor gives another answer (not only a rigid motion of
  this one): the derivative belongs to this anchor.
* otherwise (``refine=None``, the default, or ``True``) -- the **nearest surface**, the
  minimizer of the refinement's energy (:mod:`solver.refine.refined_energy`), also where the forms
  integrate (there the linear answer is that minimizer, with energy 0, and any nearby forms
  are refined). Implicit differentiation of ``grad E(x*; targets) = 0`` with the **exact**
  Hessian, assembled and factorized once (a sparse Cholesky of order 3n, the pattern of the
  refinement's Gauss-Newton matrix). The Gauss-Newton matrix alone would differ from it by
  ``sum_r r_r Hess(r_r)``, which does not vanish away from exact fits (noisy or scaled
  forms: docs/differentiable.md measures the error it would cost). The optimum is only
  defined up to a rigid motion of each unconstrained component; the gauge is that of
  :meth:`solver.reconstruct.ImmersionProblem.place_anchored` (anchor vertex at the origin,
  the nearest rotation of the anchor face's layout frame the identity), and the VJP
  differentiates exactly that placement, so a loss invariant to rigid motions gets the
  gradient it would get in any other gauge. Before differentiating, ``polish=True`` (the
  default) takes Newton steps with the exact Hessian from the refinement's answer until the
  step is below :data:`solver.adjoints.POLISH_TOLERANCE` of the mean edge length
  (``result.vertices`` are then the polished optimum; ``report["vjp"]`` says how far it
  moved), since the implicit function theorem holds at the optimum, not at a point within
  the refinement's looser stopping tolerance.

Forms of a real file (:func:`solver.fundamental_forms` of a non-manifold mesh, or of one with
vertices joined by zero-length edges) carry ``vertex_map`` and ``weld_map``, and forms of
several parts a ``placement``: pass them as to :func:`solver.reconstruct`. The adjoint then
works on the solved (cut) mesh in the solver's gauge, with the cut's own answer (not the
mean of the copies, which may spread for noisy forms), and the cotangent, given per FILE
vertex, is pulled back through what :func:`solver.reconstruct` does after solving
(:mod:`solver.answer_map`): the placement's rigid motion of each part (or the side-by-side
layout of parts without one), the mean over each file vertex's copies and the weld.
Constraints name file vertices, as in :func:`solver.reconstruct` (a split vertex's first
copy; a welded vertex's representative).

Not differentiated (a :class:`solver.core.errors.ConstraintError` says so): cotangent
weightings, ``layout_angles``, ``orthonormalize=True`` with ``refine=False``, and
constraints that leave a gauge to the regularization (``report["regularized_components"]``).
Where constraints leave some rigid motion of a component free in the refined answer (one or
two hard vertices), the cotangent's component along those motions is dropped (the answer
is not defined along them).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .adjoints import FormCotangents, LinearAdjoint, RefinedAdjoint
from .answer_map import AnswerMap
from .core.errors import ConstraintError
from .immersion import ImmersionProblem
from .mesh.alignment import kabsch
from .mesh.forms import validate_forms
from .options import ReconstructOptions
from .reconstruct import Reconstruction, reconstruct_on_cut


class ReconstructionVJP:
    """Vector-Jacobian product of one reconstruction.

    Call it with a cotangent ``g`` of ``result.vertices`` ((n, 3) or (k, n, 3)) to get
    ``(grad_lengths, grad_angles)``. Made by :func:`reconstruct_vjp`.

    Args:
        adjoint: the linear or refined adjoint that computes the cotangents (on the solved
            mesh, in the solver's gauge).
        answer: the map from that answer to ``result.vertices`` (placement, side-by-side
            layout, file vertices of a cut mesh: :mod:`solver.answer_map`).
        report: what preparing it cost.

    Attributes:
        mode: ``"linear"`` or ``"refined"`` (see the module docstring).
        report: what preparing it cost (``seconds``, ``factorizations``) and, refined, the
            polishing (``polish_steps``, ``polish_moved`` relative to the mean edge length,
            ``gradient_norm``).
    """

    def __init__(self, adjoint: LinearAdjoint | RefinedAdjoint, answer: AnswerMap,
                 report: dict[str, Any]) -> None:
        self._adjoint = adjoint
        self._answer = answer
        self.mode = "linear" if isinstance(adjoint, LinearAdjoint) else "refined"
        self.n_vertices = answer.n_vertices
        self.report = report

    def cotangents(self, g: ArrayLike) -> FormCotangents:
        """All cotangents of the reconstruction's inputs.

        Args:
            g: (n, 3) or (k, n, 3) float cotangent of ``result.vertices``.

        Returns:
            :class:`FormCotangents` (with a leading axis k when ``g`` had one).

        Raises:
            ConstraintError: ``g`` of the wrong shape or not finite.
        """
        g = np.asarray(g, dtype=np.float64)
        single = g.ndim == 2
        batch = g[None] if single else g
        if batch.ndim != 3 or batch.shape[1:] != (self.n_vertices, 3):
            raise ConstraintError(f"the cotangent must have shape ({self.n_vertices}, 3) or "
                                  f"(k, {self.n_vertices}, 3), got {g.shape}", field="cotangent")
        if not np.isfinite(batch).all():
            raise ConstraintError("the cotangent has non-finite values", field="cotangent")
        if not self._answer.is_identity:    # to the solver's answer on the solved mesh
            batch = self._answer.vjp(self._solved_vertices(), batch)
        out = self._adjoint.vjp(batch)
        if single:
            out = FormCotangents(*(a[0] for a in (out.lengths, out.angles, out.positions,
                                                  out.frames)))
        return out

    def _solved_vertices(self) -> np.ndarray:
        """(n_cut, 3) the differentiated answer on the solved mesh, in the solver's gauge."""
        adjoint = self._adjoint
        if isinstance(adjoint, RefinedAdjoint):
            return adjoint.vertices
        return adjoint.problem.unknowns_to_geometry(adjoint.u.copy(), adjoint.user)[0]

    def __call__(self, g: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """``(grad_lengths, grad_angles)``, (E,) or (k, E) float64, for ``g`` (n, 3) or
        (k, n, 3) (:meth:`cotangents`)."""
        out = self.cotangents(g)
        return out.lengths, out.angles


def reconstruct_vjp(faces: ArrayLike, edges: ArrayLike, lengths: ArrayLike, angles: ArrayLike,
                    *, options: ReconstructOptions | None = None, polish: bool = True,
                    **keywords: Any) -> tuple[Reconstruction, ReconstructionVJP]:
    """:func:`solver.reconstruct` and its vector-Jacobian product (module docstring).

    Args:
        faces, edges, lengths, angles: as for :func:`solver.reconstruct`.
        options: :class:`solver.options.ReconstructOptions`, as for :func:`solver.reconstruct`
            (keyword overrides of its fields too); the adjoint differentiates the answer of
            exactly these options.
        polish: refined answers only: Newton steps to the optimum before differentiating.
        **keywords: the other keywords of :func:`solver.reconstruct` (``constraints``,
            ``n_vertices``, ``progress``, ``vertex_map``, ``weld_map``, ``placement``, ...)
            and option overrides.

    Returns:
        ``(result, vjp)``: the :class:`Reconstruction` (``report["vjp"]`` added) and a
        :class:`ReconstructionVJP`.

    Raises:
        ConstraintError: an option or constraint set it does not differentiate (cotangent
            weightings, ``layout_angles``, orthonormalized linear answers, a regularized
            gauge).
        SolverInputError: any error :func:`solver.reconstruct` raises.
    """
    names = ReconstructOptions.names()
    options = ReconstructOptions.given(
        options, {k: keywords.pop(k) for k in list(keywords) if k in names})
    _check_supported(options, keywords)
    result, solved = reconstruct_on_cut(faces, edges, lengths, angles, options=options,
                                        **keywords)
    if result.report.get("regularized_components"):
        raise ConstraintError("reconstruct_vjp does not differentiate the regularized gauge "
                              "of constraints that leave a component's gauge free "
                              f"(components {result.report['regularized_components']})",
                              field="constraints")
    started = time.perf_counter()
    answer = solved.answer
    topology, L, A = validate_forms(faces, edges, lengths, angles, answer.n_solved)
    user = solved.constraints
    problem = ImmersionProblem(topology, L, A, frame_weight=options.frame_weight,
                               weighting="uniform", length_scale=options.length_scale)
    backend = options.backend or "auto"
    if options.refine is False:
        adjoint: LinearAdjoint | RefinedAdjoint = LinearAdjoint(
            problem, user, L, backend, options.length_scale is None)
        adjoint.check(solved.vertices)
        report: dict[str, Any] = {"mode": "linear", "factorizations": 1}
    else:
        gauge = result if answer.is_identity else Reconstruction(
            vertices=solved.vertices, frames=result.frames, report=result.report)
        adjoint = RefinedAdjoint(problem, user, L, A, gauge, options.angle_weight, backend,
                                 polish)
        report = {"mode": "refined", **adjoint.report}
        vertices, frames, _ = answer.forward(adjoint.vertices,
                                             problem.frames_of(adjoint.vertices))
        result = Reconstruction(vertices=vertices, frames=frames, report=result.report)
    report["seconds"] = time.perf_counter() - started
    result.report["vjp"] = report
    return result, ReconstructionVJP(adjoint, answer, report)


def _check_supported(options: ReconstructOptions, keywords: dict[str, Any]) -> None:
    """Raise :class:`ConstraintError` for options :func:`reconstruct_vjp` cannot differentiate."""
    if options.weighting != "uniform":
        raise ConstraintError("reconstruct_vjp differentiates the uniform weighting only",
                              field="options.weighting")
    if keywords.get("layout_angles") is not None:
        raise ConstraintError("reconstruct_vjp does not take layout_angles",
                              field="options.layout_angles")
    if options.orthonormalize and options.refine is False:
        raise ConstraintError("reconstruct_vjp does not differentiate the orthonormalized "
                              "linear answer (refine=False with orthonormalize=True)",
                              field="options.orthonormalize")
    if "progress" in keywords and keywords["progress"] is not None and not callable(
            keywords["progress"]):
        raise ConstraintError("progress must be callable", field="progress")


def aligned_distance(vertices: ArrayLike, target: ArrayLike) -> tuple[float, np.ndarray]:
    """A loss invariant to rigid motions of ``vertices``, and its gradient.

    ``loss = min_{R, t} sum_v |R x_v + t - y_v|^2 / (n s^2)`` over rotations R and
    translations t (Kabsch), ``s`` the target's RMS distance from its centroid; by the
    envelope theorem its gradient (n, 3) is ``2 (R x + t - y) R / (n s^2)`` at the optimal
    (R, t).

    Args:
        vertices: (n, 3) float.
        target: (n, 3) float.

    Returns:
        ``(loss, gradient)``: a float and (n, 3) float64.

    Example:
        A rotated and shifted copy is at distance 0; a scaled one is not:

        >>> import numpy as np
        >>> from solver.differentiable import aligned_distance
        >>> from solver.mesh.rotations import rotation_z
        >>> target = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> moved = target @ rotation_z(np.array([0.7]))[0].T + 3.0
        >>> loss, gradient = aligned_distance(moved, target)
        >>> bool(loss < 1e-20), gradient.shape
        (True, (4, 3))
        >>> round(aligned_distance(2.0 * target, target)[0], 12)
        1.0
    """
    X = np.asarray(vertices, dtype=np.float64)
    Y = np.asarray(target, dtype=np.float64)
    rotations, centers, target_centers = kabsch(X, Y)
    R, x0, y0 = rotations[0], centers[0], target_centers[0]      # R (x - x0) ~ y - y0
    residual = (X - x0) @ R.T + y0 - Y
    norm = len(X) * float(np.mean(np.sum((Y - y0) ** 2, axis=1)))
    return float(np.sum(residual**2)) / norm, 2.0 * residual @ R / norm
