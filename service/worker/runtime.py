"""The worker process's side of a task: set-up, stage timing, and failures as dicts.

A process of this service (a local pool worker, a session process) calls
:func:`start_worker_process` first, a Dask worker :func:`initialize_worker` once; then
:func:`service.operations.run` per task, which times its stages with :class:`StageClock`.
A task's failure leaves the process as a plain dict
(:func:`service.api.problems.failure_of`), never as a pickled exception;
:meth:`service.api.problems.ProblemError.from_dict` turns it back into the problem on the
HTTP side.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import time
from collections.abc import Callable
from typing import Any

from ffs_wire.progress import PROGRESS_INTERVAL, ProgressThrottle

Progress = Callable[..., None]
ITERATION_FIELDS: tuple[str, ...] = ("iteration", "factorizations", "energy", "seconds")
"""What a job reports of each refinement step (``progress.refinement``)."""
__all__ = ["ITERATION_FIELDS", "PROGRESS_INTERVAL", "Progress", "ProgressThrottle", "StageClock",
           "initialize_worker", "start_worker_process"]
"""(:data:`PROGRESS_INTERVAL` and :class:`ProgressThrottle` live in :mod:`ffs_wire.progress`,
shared with ``ffs -j N``'s worker processes.)"""
logger = logging.getLogger("service.worker")


def start_worker_process(threads: int) -> None:
    """First thing in a worker or session process of this service: cap the threads of numpy
    and MKL before they load (MKL reads the variables only at load time), leave Ctrl-C to
    the parent, which shuts the process down, then :func:`initialize_worker`."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    initialize_worker(threads)


def initialize_worker(threads: int) -> None:
    """Warm a worker: load the sparse backends and the mesh file readers once (the first
    upload would otherwise import trimesh within its deadline: 0.4 s of a 0.55 s
    FFS_REQUEST_TIMEOUT), cap BLAS/MKL threads, and move every
    object loaded so far out of the garbage collector's sight (``gc.freeze``: the modules
    of numpy, scipy, pydantic... are never garbage, and each collection would traverse
    them again)."""
    from solver import linalg
    from solver.mesh.io import import_readers

    linalg.available_backends()
    import_readers()
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(threads)
    except Exception:  # threadpoolctl missing or a library it cannot control
        pass
    gc.collect()
    gc.freeze()


class StageClock:
    """Wraps ``progress(stage, fraction)`` and measures the wall time of each stage.

    The solver's refinement also calls :meth:`iteration` after every accepted step; the
    detail travels as ``progress(stage, fraction, detail)`` (a job's status document shows
    it as ``progress.refinement``)."""

    def __init__(self, progress: Progress) -> None:
        self._progress = progress
        self.stage: str | None = None
        self._fraction = 0.0
        self._since = time.perf_counter()
        self.timings: dict[str, float] = {}

    def __call__(self, stage: str, fraction: float) -> None:
        self._lap(stage)
        self._fraction = fraction
        self._progress(stage, fraction)

    def iteration(self, detail: dict[str, Any]) -> None:
        """A refinement step: ``{"iteration", "factorizations", "energy", "seconds"}``."""
        self._progress(self.stage or "refine", self._fraction,
                       {key: detail[key] for key in ITERATION_FIELDS})

    def _lap(self, stage: str | None) -> None:
        now = time.perf_counter()
        if stage != self.stage:
            if self.stage is not None:
                self.timings[self.stage] = self.timings.get(self.stage, 0.0) + now - self._since
            self.stage, self._since = stage, now

    def finish(self) -> dict[str, float]:
        self._lap(None)
        return self.timings
