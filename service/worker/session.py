"""The warm side of a deformation session: one prefactorized :class:`solver.Deformer`.

A backend keeps one :class:`SessionState` alive with exactly one worker (a dedicated
process locally, a Dask actor on a cluster); every drag only back-substitutes and encodes.

A session opened with ``options.refine: true`` is *progressive*: :meth:`SessionState.solve`
answers the linear shape at once and leaves the drag's refinement pending; the worker then
calls :meth:`SessionState.refine_slice` while no newer drag is waiting (a new drag is never
delayed by more than one slice), and the last slice yields the refined shape
(:class:`Refined`). A newer drag supersedes a pending refinement. The first slice waits
until the drags pause (:meth:`SessionState.refine_due`): while the user drags on, each
drag's linear shape comes without waiting for a refinement slice.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.api.budgets import TIME_POLICY
from service.api.task import SessionSpec
from service.worker import output

DRAG_PAUSE = 0.03
"""Seconds without a newer drag after which a progressive session starts refining (an
interactive client sends its next drag within milliseconds of a linear answer)."""
SESSION_FORMATS: tuple[str, ...] = ("json", "glb", "gltf", "f32")
"""Response formats of a session solve, in server preference order."""


def encode_vertices(vertices: np.ndarray, faces: np.ndarray, fmt: str,
                    fields: dict[str, Any] | None = None) -> bytes:
    """The body of a solve in format ``fmt`` (see :data:`SESSION_FORMATS`): ``f32`` is
    little-endian float32 (n, 3), ready for a vertex buffer; JSON also carries ``fields``
    (a progressive session's ``shape``, ``drag``, ``refinement``)."""
    if fmt == "f32":
        return np.ascontiguousarray(vertices, dtype="<f4").tobytes()
    if fmt == "json":
        return output.json_bytes({"vertices": vertices, **(fields or {})})
    if fmt == "f64":  # not offered over HTTP; exact float64 for tests
        return np.ascontiguousarray(vertices, dtype="<f8").tobytes()
    return output.mesh_bytes(fmt, vertices, faces)


@dataclass(frozen=True)
class Refined:
    """The refined shape of drag ``drag``, encoded like its linear answer, and how it refined
    (:meth:`SessionState.refine_slice`)."""

    drag: int
    body: bytes
    report: dict[str, Any]
    fmt: str = "json"


@dataclass
class _Pending:
    """A drag whose refinement is not finished: its answer format and the totals so far."""

    drag: int
    fmt: str
    iterations: int = 0
    factorizations: int = 0
    slices: int = 0
    slice_seconds: float = 0.0
    """The shortest slice so far that iterated: a slice that ended before its first
    iteration doubles it, so a slice too short for one iteration on this mesh and machine
    still progresses, and the next slices keep the length that worked."""
    seconds: float = 0.0
    start: str | None = None
    started: float = field(default_factory=time.perf_counter)


class SessionState:
    """A :class:`solver.Deformer` factorized at init, and a first solve at rest that checks
    the factorization (and warms the backend up). ``solve_timeout``: the backend's
    (``FFS_SESSION_SOLVE_TIMEOUT``); :attr:`refine_seconds`, the most one drag's refinement
    may take in all, is :meth:`TimePolicy.drag_budget
    <service.api.budgets.TimePolicy.drag_budget>` of it and ``options.max_seconds``."""

    def __init__(self, spec: SessionSpec, solve_timeout: float) -> None:
        import solver

        options = spec.deform_options()
        start = time.perf_counter()
        # A Deformer reads refine=None as off (solver.options.DeformOptions): linear drags.
        self.progressive = options.refine is True
        self.refine_seconds = TIME_POLICY.drag_budget(options.max_seconds, solve_timeout)
        self.deformer = solver.Deformer(  # (a progressive one builds its start-up fit now)
            spec.vertices, spec.faces, spec.handles, rotation_handles=list(spec.rotations) or None,
            roi=spec.roi, options=options)
        self.deformer.solve(refine=False)
        self.setup_seconds = time.perf_counter() - start
        self.faces = self.deformer.file_faces  # a non-manifold mesh is solved on its cut
        self.solves = 0
        self.drags = 0
        """Drags answered so far; drag k (1, 2, ...) is the k-th."""
        self.pending: _Pending | None = None

    def info(self) -> dict[str, Any]:
        """Sizes, handles, set-up time, linear-solver backend and whether drags refine."""
        d = self.deformer
        return {"n_vertices": len(d.file_rest), "n_faces": len(d.file_faces),
                "handles": [int(h) for h in d.file_handles], "n_rotation_groups": d.n_groups,
                "setup_seconds": self.setup_seconds, "backend": d.backend,
                "refine": self.progressive}

    def solve(self, positions: np.ndarray, rotations: np.ndarray | None,
              fmt: str) -> tuple[bytes, dict[str, float], int]:
        """The linear shape for new handle targets, encoded; stage timings; the drag's
        number. A progressive session's drag is left to refine (:attr:`pending`),
        superseding the previous one's refinement."""
        t0 = time.perf_counter()
        vertices = self.deformer.solve(positions, rotations, refine=False)
        t1 = time.perf_counter()
        self.solves += 1
        self.drags += 1
        body = encode_vertices(vertices, self.faces, fmt, {"shape": "linear", "drag": self.drags}
                               if self.progressive else None)
        self.pending = _Pending(self.drags, fmt) if self.progressive else None
        return body, {"solve": t1 - t0, "encode": time.perf_counter() - t1}, self.drags

    def refine_due(self) -> float:
        """Seconds until the pending drag's refinement should start: a drag refines once no
        newer one came for :data:`DRAG_PAUSE` seconds after its linear answer (0: now, or it
        has started already)."""
        pending = self.pending
        if pending is None or pending.slices:
            return 0.0
        return max(0.0, pending.started + DRAG_PAUSE - time.perf_counter())

    def refine_slice(self, seconds: float) -> Refined | None:
        """Refine the pending drag for about ``seconds`` (the refinement does not start an
        iteration that, timed like the last one of its kind, would end past the slice; after
        a slice that ended before its first iteration the next one is twice as long, so
        every refinement progresses); the refined shape once it
        converged, stopped otherwise, or spent :attr:`refine_seconds` or the refinement's
        iteration limit in all; None while it goes on (call again)."""
        from solver.refine.stopping import DEFAULT_STOP_RULES

        max_iterations = DEFAULT_STOP_RULES.max_iterations

        pending = self.pending
        if pending is None:
            return None
        left = self.refine_seconds - pending.seconds
        t0 = time.perf_counter()
        budget = max(seconds, pending.slice_seconds)
        vertices = self.deformer.refine_last(max(0.0, min(budget, left)))
        report = self.deformer.last_report
        pending.slices += 1
        # A slice continues the drag's refinement (Deformer.refine_last): its report counts
        # the whole refinement so far.
        iterations = int(report.get("iterations", 0))
        pending.slice_seconds = budget if iterations > pending.iterations else 2.0 * budget
        pending.iterations = iterations
        pending.factorizations = int(report.get("factorizations", 0))
        pending.seconds += time.perf_counter() - t0
        pending.start = pending.start or report.get("start")
        stop = report.get("stop_reason") if report.get("refined") else "exact"
        converged = bool(report.get("converged")) or stop == "exact"
        if stop == "time_limit" and pending.seconds < self.refine_seconds \
                and pending.iterations < max_iterations:
            return None
        if stop == "time_limit" and pending.iterations >= max_iterations:
            stop = "max_iterations"
        self.pending = None
        summary = {"converged": converged, "stop_reason": stop,
                   "iterations": pending.iterations, "factorizations": pending.factorizations,
                   "slices": pending.slices, "seconds": pending.seconds,
                   "elapsed": time.perf_counter() - pending.started,
                   "energy": report.get("energy_after"), "start": pending.start}
        body = encode_vertices(vertices, self.faces, pending.fmt, {
            "shape": "refined", "drag": pending.drag, "refinement": summary})
        return Refined(pending.drag, body, summary, pending.fmt)
