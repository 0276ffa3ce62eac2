"""What runs on a Dask worker: :func:`run_task` (one task) and :class:`SessionActor`.

Failures come back as values (the same failure dicts as the local pool), so Dask retries
only what dies with its worker. A job's progress goes to the scheduler as events
(:data:`~service.backends.dask.registry.PROGRESS_TOPIC`), where the registry folds it into
the job's record.
"""

from __future__ import annotations

import os
import threading
import time
import weakref
from typing import Any

import numpy as np

from service.api.task import SessionSpec, TaskRequest
from service.backends.admission import estimate_memory
from service.backends.dask.registry import PROGRESS_TOPIC
from service.memory import free_deferred, process_memory

_initialized: set[int] = set()


def _init_worker(threads: int) -> None:
    """Warm this worker process once (the backends, the thread caps)."""
    pid = os.getpid()
    if pid not in _initialized:
        from service.worker import runtime

        runtime.initialize_worker(threads)
        _initialized.add(pid)


class _EventProgress:
    """``progress(stage, fraction, detail=None)`` -> scheduler events, one per report
    :func:`service.operations.run` lets through (its
    :class:`~service.worker.runtime.ProgressThrottle`: at most 5 a second, the last always;
    a refinement iteration's ``detail`` with them)."""

    def __init__(self, job_id: str) -> None:
        from distributed import get_worker

        self.job_id = job_id
        self.worker = get_worker()

    def __call__(self, stage: str, fraction: float,
                 detail: dict[str, Any] | None = None) -> None:
        event: dict[str, Any] = {"id": self.job_id, "stage": stage, "fraction": float(fraction)}
        if detail is not None:
            event["detail"] = detail
        self.worker.log_event(PROGRESS_TOPIC, event)

    def fail(self, error: dict[str, Any]) -> None:
        self.worker.log_event(PROGRESS_TOPIC, {"id": self.job_id, "error": error})


def run_task(request: TaskRequest, job_id: str | None = None,
             threads: int = 1) -> dict[str, Any]:
    """A task on a Dask worker: ``{"ok": True, "result"}`` or ``{"ok": False, "error"}``."""
    from service import operations
    from service.api.problems import failure_of

    _init_worker(threads)
    report = _EventProgress(job_id) if job_id else None
    try:
        result = operations.run(request, report or (lambda stage, fraction, detail=None: None))
    except Exception as exc:
        error = failure_of(exc)
        if report is not None:
            report.fail(error)
        return {"ok": False, "error": error}
    finally:
        free_deferred()  # the parsed body: Dask sends the result after this returns
    return {"ok": True, "result": result}


class _Refinery:
    """A progressive session's refinement on a Dask worker: a thread refines the newest
    drag slice by slice (:meth:`SessionState.refine_slice
    <service.worker.session.SessionState.refine_slice>`) between the actor's calls, which
    take :attr:`lock` (a drag waits at most one slice). The thread holds the refinery only
    weakly: when the actor is released it ends."""

    def __init__(self, state: Any, slice_seconds: float) -> None:
        self.state = state
        self.slice = slice_seconds
        self.lock = threading.Lock()
        self.work = threading.Event()
        self.waiting = 0  # callers waiting for the lock: the thread lets them in first
        self.refined: tuple[int, Any] | None = None  # (drag, Refined or failure dict)
        threading.Thread(target=_refine_forever, args=(weakref.ref(self),), daemon=True,
                         name="ffs-session-refine").start()

    def step(self) -> bool:
        """One slice of the pending drag's refinement; False when there is none."""
        from service.api.problems import failure_of

        while self.waiting:  # a drag or a poll is waiting: let it in
            time.sleep(0.0005)
        due = self.state.refine_due()  # the drags have not paused yet
        if due > 0:
            time.sleep(min(due, 0.005))
            return self.state.pending is not None
        with self.lock:
            pending = self.state.pending
            if pending is None:
                self.work.clear()
                return False
            try:
                refined = self.state.refine_slice(self.slice)
            except Exception as exc:
                self.state.pending = None
                self.refined = (pending.drag, failure_of(exc))
            else:
                if refined is not None:
                    self.refined = (refined.drag, refined)
            return True


def _refine_forever(ref: weakref.ref[_Refinery]) -> None:
    while True:
        refinery = ref()
        if refinery is None:
            return
        work = refinery.work
        if not refinery.step():
            del refinery  # (only the actor keeps it alive while the thread waits)
            work.wait(1.0)


class SessionActor:
    """A session on a Dask worker (an actor: its state stays on that worker). A progressive
    session refines in a thread of its own (:class:`_Refinery`)."""

    def __init__(self, spec: SessionSpec, threads: int, solve_timeout: float,
                 refine_slice: float) -> None:
        from distributed import get_worker

        from service.api.problems import failure_of
        from service.worker.session import SessionState

        _init_worker(threads)
        self.worker = get_worker().address
        self.error: dict[str, Any] | None = None
        self.state: SessionState | None = None
        estimate = estimate_memory(len(spec.vertices), len(spec.faces))
        before = process_memory()
        self.refinery: _Refinery | None = None
        try:
            self.state = SessionState(spec, solve_timeout)
        except Exception as exc:
            self.error = failure_of(exc)
        else:
            if self.state.progressive:
                self.refinery = _Refinery(self.state, refine_slice)
        grown = process_memory() - before
        # Memory growth of the shared worker process is a rough measure (other tasks run
        # there too); it never counts for less than half the estimate.
        self.memory = max(grown, estimate // 2)

    def info(self) -> dict[str, Any]:
        if self.state is None:
            return {"error": self.error}
        return {"info": self.state.info(), "memory": self.memory, "worker": self.worker}

    def solve(self, positions: np.ndarray, rotations: np.ndarray | None,
              fmt: str) -> tuple[str, Any, Any]:
        from service.api.problems import failure_of

        assert self.state is not None
        refinery = self.refinery
        if refinery is None:
            try:
                body, timings, drag = self.state.solve(positions, rotations, fmt)
            except Exception as exc:
                return ("error", failure_of(exc), None)
            return ("ok", body, timings, drag, False)
        refinery.waiting += 1
        try:
            with refinery.lock:
                refinery.waiting -= 1
                try:
                    body, timings, drag = self.state.solve(positions, rotations, fmt)
                except Exception as exc:
                    return ("error", failure_of(exc), None)
                refinery.refined = None
                refining = self.state.pending is not None
        finally:
            refinery.work.set()
        return ("ok", body, timings, drag, refining)

    def refined(self, drag: int) -> tuple[str, Any]:
        """The state of drag ``drag``'s refinement: ``("refined", Refined)``,
        ``("failed", failure)``, ``("refining", None)``, ``("superseded", newest drag)`` or
        ``("none", reason)``."""
        assert self.state is not None
        latest, refinery = self.state.drags, self.refinery
        if drag < 1 or drag > latest:
            return ("none", f"the session has answered {latest} drags")
        if drag < latest:
            return ("superseded", latest)
        if refinery is None:
            return ("none", "the session does not refine (open it with options.refine true)")
        refined = refinery.refined
        if refined is not None and refined[0] == drag:
            return ("failed" if isinstance(refined[1], dict) else "refined", refined[1])
        return ("refining", None)
