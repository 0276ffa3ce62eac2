"""How the refinement steps: line search, damping, factor reuse and precision, as data.

:class:`StepRules` holds the thresholds of :class:`solver.refine.Refiner`'s steps that are
not about stopping (those are :mod:`solver.stopping`): which step lengths the line search
tries, how Levenberg-Marquardt's damping moves, how long a factorization is kept for
quasi-Newton steps, and when a factor is computed in single precision. Why each has its
value (measurements): ``docs/refinement.md``.

Example:
    >>> import numpy as np
    >>> factor_precision(np.array([1.0, 2.0, 3.0])), factor_precision(np.array([1.0, 1e9, 1.0]))
    ('single', 'double')
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StepRules:
    """The thresholds of the refinement's steps."""

    step_fractions: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1)
    """Fractions of a step the line search tries, longest first, before the damping grows."""
    armijo: float = 1e-4
    """Sufficient decrease: ``E(x + a d) < E(x) + armijo a g.d``."""
    max_frozen_steps: int = 6
    """Steps on one factorization before it is rebuilt at the current positions."""
    frozen_gain: float = 0.5
    """A factor is rebuilt earlier when a step lowers E by less than this times its prediction;
    outside interactive runs such a step of a factor built elsewhere is refused."""
    frozen_reach: float = 0.5
    """... or when a step moved a vertex by more than this many mean edge lengths (not for a
    kept factor)."""
    kept_steps: int = 20
    """Quasi-Newton steps on a factor kept from the previous run (a session's drags), when its
    damping is at most ``kept_damping``."""
    kept_gain: float = 0.05
    """``frozen_gain`` for such a kept factor."""
    kept_damping: float = 1e-3
    """Largest relative damping of a kept factor that is kept for ``kept_steps``."""
    quasi_newton_memory: int = 8
    """L-BFGS (s, y) pairs since the factor was built, in runs that start from a kept factor
    (elsewhere the steps between factorizations are frozen Gauss-Newton steps)."""
    initial_damping: float = 1e-9
    """The first step's damping, relative to diag(J^T J)."""
    min_damping: float = 1e-12
    """The Nielsen update never lowers the damping below this."""
    refused_damping: float = 1e-4
    """At least this damping after a fresh step that no backtracking saved."""
    single_precision_spread: float = 1e3
    """Largest spread (largest over median entry) of the damped Gauss-Newton matrix's diagonal
    that is factorized in single precision (1e4 before issue 40: the scan-like stand-in of
    bench.slivers, 2662 tied needles and 26 short edges left, spread 8.2e3, had its float32
    factor refused by PARDISO, a wasted factorization of 3.2 s of 13.9; clean meshes spread
    12-200)."""
    cg_loosest: float = 1e-2
    """The iterative path's (:mod:`solver.refine.iterative_steps`) loosest forcing term: the
    relative residual of the first Gauss-Newton step's CG, and the most any step's may
    keep. 0.1 let steps stop after 1-3 CG iterations, near-gradient steps: 13 Gauss-Newton
    steps on the 400K-face scan (direct: 3); from 0.97 x the mesh, 1e-2 took 4-5 steps and
    166-203 CG iterations where 0.1 took 6 and 148-221 (rocker-arm x 0.8 and noisy,
    armadillo noisy), 7-28% less time."""
    cg_tightest: float = 1e-3
    """... its tightest forcing term: ``cg_confirm``'s, since a solve that tight already counts
    as exact for the stopping rules and the run stops at ``StopRules.energy_tolerance`` (1e-3
    of E), not where Newton's local convergence would pay. 1e-6 before: the forcing term went
    to 7e-6 near the optimum. On the noisy forms and x0.8 forms of ten shared meshes (1K-86K
    faces, ``linear_solver="iterative"``; a scratch script, not in bench/) the same
    Gauss-Newton steps, every run converged, E within 1e-9 relative, 6436 -> 5997 CG
    iterations in all, 25-30% fewer on noisy forms
    (armadillo 161 -> 111); on bench.scale's noisy 100K-face scan 8, 74, 30, 132 -> 8, 53,
    32, 61 (37-41 -> 29 CPU s), at 400K 11, 46, 40, 143 -> 11, 46, 40, 108 (163 CPU s both;
    ``python -m bench.gauss_newton_cg policies 0`` and ``1 --policies rule``); at 1.6M about
    the same work, 635 against 627 CG iterations (docs/large-meshes.md)."""
    cg_confirm: float = 1e-3
    """A Gauss-Newton step solved to at most this relative residual counts as exact for the
    stopping rules (:func:`solver.refine.stopping.after_step`); a looser one that looks
    converged is confirmed by a step solved to this tolerance."""
    cg_max_iterations: int = 300
    """CG iterations after which a Gauss-Newton step's solve stops (reported as capped)."""
    cg_resetup_growth: float = 2.0
    """The multigrid hierarchy is set up again when a solve took more than this many times
    the iterations per decade of the first solve on it (or hit the cap)."""
    cg_setup_iterations: float = 85.0
    """A multigrid setup's price in CG iterations, which the reuse rules weigh against the
    iterations a stale hierarchy costs (:class:`solver.refine.iterative_steps.Multigrid`):
    iterations, not seconds, so that the refinement's path does not depend on the machine's
    load. Measured by scalar unknowns in single precision: 84 CG iterations at 100K faces,
    87 at 400K (``python -m bench.gauss_newton_cg setup-price 0 1``, bench/README.md). A
    hierarchy per vertex in double precision (``HierarchyRules(by_vertex=True,
    dtype="float64")``, measured, not chosen) sets up in half the time and iterates at half
    the speed: 19 and 21 there. At 20 that hierarchy's 100K scan sets up a second time and
    its next solve takes the same 37 iterations as on the kept hierarchy (24.6 against 19.3
    CPU s, ``python -m bench.gauss_newton_cg policies 0 --policies rule``): the later
    solves take more
    iterations per decade because their forcing terms are tighter, not because the
    hierarchy went stale, so a setup is kept at the price that waits for 85 iterations
    beyond the first solve's rate."""
    single_precision_error: float = 0.1
    """Largest relative correction of a single-precision solve by its refinement step before
    the refiner factorizes in double precision."""


DEFAULT_STEP_RULES = StepRules()
"""The step rules every refinement uses unless given others."""


def nielsen_damping(rules: StepRules, damping: float, gain: float, alpha: float) -> float:
    """Levenberg-Marquardt's damping after a fresh step of length ``alpha`` with gain
    ratio ``gain`` (Nielsen's update; a shortened step multiplies it by 10)."""
    factor = max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3) if alpha == 1.0 else 10.0
    return max(rules.min_damping, damping * factor)


def factor_precision(diagonal: np.ndarray,
                     spread: float = DEFAULT_STEP_RULES.single_precision_spread) -> str:
    """The precision to factorize a damped Gauss-Newton matrix in, from its diagonal.

    Single precision nearly halves the factorization's time (:mod:`solver.mixed_precision`),
    and with one refinement step per solve the steps are those of double precision. Needle
    edges and flattened faces make entries of the diagonal 1e8 times the others (the
    stiffness of a residual grows as the inverse square of the edge's length or the face's
    width), beyond what float32 resolves; the diagonal's spread separates the two (12-200 on
    every bench mesh, 1.5e8 and more with needle edges). Soft modes that the diagonal does
    not show are caught by the solves themselves
    (:attr:`StepRules.single_precision_error`).

    Args:
        diagonal: (N,) float64 diagonal of the damped matrix (positive).
        spread: largest spread (largest over median entry) factorized in single precision.

    Returns:
        ``"single"`` or ``"double"``.
    """
    if not len(diagonal):
        return "double"
    ratio = float(diagonal.max()) / float(np.median(diagonal))
    return "single" if ratio <= spread else "double"
