"""The state of a refinement between its steps: :class:`IterationState`.

What :class:`solver.refine.Refiner`'s Levenberg-Marquardt iteration carries from step to
step (positions, energy, damping, the factor and its quasi-Newton memory, counters, why it
stopped), and the two things it computes from it: the next step's direction and a solve
with the factor off the rigid motions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..mesh.rigid_motions import RigidProjection
from .iterative_steps import forcing
from .mixed_precision import SinglePrecisionFactor
from .normal_equations import GaussNewtonSystem
from .quasi_newton import QuasiNewtonMemory
from .steps import DEFAULT_STEP_RULES, StepRules
from .stopping import StopReason, StopRules


@dataclass
class IterationState:
    """Everything :meth:`solver.refine.Refiner`'s iteration carries from step to step, so
    that a run stopped at its time limit resumes exactly where it stopped
    (:meth:`solver.refine.Refiner.resume`)."""

    X: np.ndarray
    before: dict[str, Any] | None  # None until the start is measured (:meth:`measured`)
    energy0: float | None
    energy: float | None
    keep_factor: bool
    interactive: bool  # loose convergence on kept factors (Refiner.run's ``interactive``)
    kept: bool
    max_frozen: int
    min_gain: float
    memory: QuasiNewtonMemory
    rules: StopRules
    factor: Any = None
    model: sp.csr_array | None = None
    projection: RigidProjection | None = None  # off the rigid motions where factor was built
    damping: float = DEFAULT_STEP_RULES.initial_damping
    growth: float = 2.0
    fresh: bool = False  # whether ``factor`` was computed at the current X
    factor_gain: float = 0.0  # gain ratio of the last step taken with ``factor``
    frozen_steps: int = 0
    iterations: int = 0
    rejected: int = 0
    factorizations: int = 0
    precisions: set[str] = field(default_factory=set)  # of the factorizations
    solves: int = 0
    slices: int = 1
    stop: StopReason | None = None
    converged: bool = False
    trace: list[float] = field(default_factory=list)
    steps: list[float] = field(default_factory=list)
    forcing: tuple[int, float, float] | None = None  # iterative path: (iteration, eta, |g|)
    confirm: bool = False  # iterative path: the next step must be solved tightly

    @classmethod
    def start(cls, X: np.ndarray, energy: float | None,
              kept: tuple[Any, sp.csr_array, RigidProjection] | None, kept_damping: float,
              keep_factor: bool, rules: StopRules, steps: StepRules) -> IterationState:
        """The state before the first step from ``X`` (n, dim) at energy ``energy`` (None:
        not known yet), its residuals not yet measured (:meth:`measured`: the first
        iteration's evaluation at ``X`` gives both). With ``keep_factor`` the previous run's
        factor, matrix and
        projection (``kept``) and its damping are the first model: consecutive drags of a
        session are alike; a run that starts from a lightly damped kept factor keeps its
        factors longer (:attr:`StepRules.kept_steps`)."""
        factor, model, projection = kept if keep_factor and kept else (None, None, None)
        damping = kept_damping if factor is not None else steps.initial_damping
        kept_long = factor is not None and damping <= steps.kept_damping
        max_frozen, min_gain = ((steps.kept_steps, steps.kept_gain) if kept_long
                                else (steps.max_frozen_steps, steps.frozen_gain))
        return cls(X=X, before=None, energy0=energy, energy=energy,
                   keep_factor=keep_factor, interactive=keep_factor, kept=kept_long,
                   max_frozen=max_frozen, min_gain=min_gain,
                   memory=QuasiNewtonMemory(steps.quasi_newton_memory if kept_long else 0),
                   rules=rules, factor=factor, model=model, projection=projection,
                   damping=damping, factor_gain=1.0 if factor is not None else 0.0,
                   trace=[] if energy is None else [energy])

    def measured(self, energy: float, before: dict[str, Any]) -> None:
        """The start's energy (unless the caller gave it) and residual summaries
        (:func:`solver.refine.form_energy.form_residuals`), once measured."""
        if self.energy0 is None:
            self.energy0 = self.energy = energy
            self.trace = [energy]
        self.before = before

    def direction(self, g: np.ndarray, system: GaussNewtonSystem,
                  ) -> tuple[np.ndarray, float, float]:
        """The step from here for the gradient ``g`` (n_free * dim,), its slope ``g.step``
        and the decrease of E its model predicts: the Gauss-Newton step on a fresh factor,
        else the L-BFGS step with the factor as initial Hessian (whose model along the
        step predicts ``-slope / 2``). Raises :class:`ImpreciseSolveError` (from
        :meth:`solve`)."""
        if self.fresh:
            step = -self.solve(g)
            slope = float(np.einsum("i,i->", g, step))  # < 0: H + D is SPD
            # Gain ratio of the full step: actual decrease over the model's.
            return step, slope, -slope - 0.5 * system.quadratic_form(self.model, step)
        step = -self.memory.inverse_hessian(self.solve, g)
        slope = float(np.einsum("i,i->", g, step))
        return step, slope, -0.5 * slope

    def solve(self, v: np.ndarray) -> np.ndarray:
        """``factor^-1 v`` (n_free * dim,) without its rigid motions
        (:mod:`solver.mesh.rigid_motions`: a factor used away from where it was built would
        otherwise turn the damping's inverse into a huge linearized rotation).

        A single-precision factor (:class:`~solver.refine.mixed_precision.SinglePrecisionFactor`)
        refines its answer by one more back-substitution, counted in ``solves``, and
        raises :class:`~solver.refine.mixed_precision.ImpreciseSolveError` where that corrects
        it by more than :attr:`StepRules.single_precision_error`."""
        if isinstance(self.factor, SinglePrecisionFactor):
            self.solves += 1  # its refinement step's back-substitution
            return self.factor.solve(v, self.projection)
        x = self.factor.solve(v)
        return x if self.projection is None else self.projection(x)

    def forcing_for(self, g: np.ndarray, steps: StepRules) -> float:
        """The iterative path's CG tolerance for this iteration's gradient ``g``: the
        Eisenstat-Walker forcing term (:func:`solver.refine.iterative_steps.forcing`), the
        same for every refresh of one iteration (more damping at the same positions), at
        most :attr:`StepRules.cg_confirm` where a step must confirm convergence."""
        norm = float(np.linalg.norm(g))
        if self.forcing is not None and self.forcing[0] == self.iterations:
            return self.forcing[1]
        previous = self.forcing
        eta = forcing(None if previous is None else previous[1], norm,
                      None if previous is None else previous[2], steps.cg_loosest,
                      steps.cg_tightest)
        if self.confirm:  # a step that looked converged: confirmed by a tight solve
            eta, self.confirm = min(eta, steps.cg_confirm), False
        self.forcing = (self.iterations, eta, norm)
        return eta

    def end(self, reason: StopReason) -> None:
        """Stop for ``reason`` (converged or not, as the reason says)."""
        self.stop, self.converged = reason, reason.converged

    def counters(self) -> dict[str, Any]:
        """The report's fields of the refinement so far."""
        stop = None if self.stop is None else self.stop.value
        return {"converged": self.converged, "stop_reason": stop,
                "iterations": self.iterations, "rejected_steps": self.rejected,
                "factorizations": self.factorizations,
                "precision": ("mixed" if len(self.precisions) > 1
                              else next(iter(self.precisions), "double")),
                "solves": self.solves,
                "slices": self.slices, "energy_before": self.energy0,
                "energy_after": self.energy, "energy_trace": list(self.trace),
                "step_trace": list(self.steps), "before": self.before}
