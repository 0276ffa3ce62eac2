"""A job's record: state, progress by stage, timings, failure. Shared by every backend.

The local backend keeps :class:`Job` objects in memory; the Dask backend keeps them in the
scheduler and ships their fields (:func:`job_fields`) to the replicas. ``error`` is the
failure dict of a failed job (:func:`service.api.problems.failure`, or the worker's
:func:`service.api.problems.failure_of`); the HTTP edge renders it as a problem document
(:meth:`service.api.problems.ProblemError.from_dict`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from service.api.task import TaskResult

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL = ("succeeded", "failed", "cancelled")


@dataclass
class Job:
    """One asynchronous job (times are ``time.time()`` seconds)."""

    id: str
    operation: str
    color: str | None = None
    owner: str | None = None
    """Who submitted it (the client's address), for the per-client limit."""
    status: str = "queued"
    created_at: float = field(default_factory=time.time)
    started_at: float | None = None
    finished_at: float | None = None
    expires_at: float | None = None
    stages: dict[str, float] = field(default_factory=dict)
    stage: str | None = None
    stage_started: float | None = None
    timings: dict[str, float] = field(default_factory=dict)
    error: dict[str, Any] | None = None
    refinement: dict[str, Any] | None = None
    """The refinement's last iteration ``{"iteration", "factorizations", "energy",
    "seconds"}`` (:data:`service.worker.runtime.ITERATION_FIELDS`), once one was taken."""
    result: TaskResult | None = None

    def __post_init__(self) -> None:
        if not self.stages:
            from service.operations import OPERATIONS

            spec = OPERATIONS.get(self.operation)
            self.stages = dict.fromkeys(spec.stages if spec else ("solve",), 0.0)

    @property
    def done(self) -> bool:
        """Whether the job reached a terminal state."""
        return self.status in TERMINAL

    def mark_running(self) -> None:
        """Move a queued job to ``running`` and record how long it waited."""
        if self.status == "queued":
            self.status = "running"
            self.started_at = time.time()
            self.timings["queued"] = self.started_at - self.created_at

    def update_progress(self, stage: str, fraction: float,
                        detail: dict[str, Any] | None = None) -> None:
        """Record a solver's ``progress(stage, fraction, detail)``.

        Earlier stages are complete, later ones are not (a solver may go back, e.g. from a
        failed shortcut to the factorization).

        Args:
            stage: the stage the solver is in.
            fraction: how far it is, 0 to 1.
            detail: a refinement iteration (:attr:`refinement`), or None.
        """
        if self.done:
            return
        self.mark_running()
        if detail is not None:
            self.refinement = dict(detail)
        now = time.time()
        previous = self.stage
        if stage != self.stage:
            if self.stage is not None and self.stage_started is not None:
                self.timings[self.stage] = (self.timings.get(self.stage, 0.0)
                                            + now - self.stage_started)
            self.stage, self.stage_started = stage, now
        names = list(self.stages)
        if stage not in names:
            return
        at = names.index(stage)
        fraction = min(1.0, max(0.0, fraction))
        if previous in names and names.index(previous) > at:
            # Back to an earlier stage (e.g. the tree integration reported `solve`, did not
            # reproduce the forms, and the solver now factorizes): the later stages are not
            # done, and this one is only as far as it says.
            for later in names[at:]:
                self.stages[later] = 0.0
        for earlier in names[:at]:
            self.stages[earlier] = 1.0
        self.stages[stage] = max(self.stages[stage], fraction)

    def finish(self, status: str, ttl: float) -> None:
        """Mark the job finished.

        Args:
            status: one of :data:`TERMINAL`.
            ttl: seconds the finished record is kept.
        """
        now = time.time()
        if self.stage is not None and self.stage_started is not None and status == "succeeded":
            self.timings.setdefault(self.stage, now - self.stage_started)
        self.status = status
        self.finished_at = now
        self.expires_at = now + ttl
        if status == "succeeded":
            self.stages = dict.fromkeys(self.stages, 1.0)
        self.stage_started = None

    @property
    def fraction(self) -> float:
        """Overall progress in [0, 1]: mean of the stage fractions."""
        if self.status == "succeeded":
            return 1.0
        return sum(self.stages.values()) / max(1, len(self.stages))


def admit(jobs: Iterable[Job], max_jobs: int, owner: str | None, max_per_owner: int
          ) -> tuple[list[str], str | None]:
    """Whether one more job fits. Finished jobs give way, oldest first, before one is refused.

    Args:
        jobs: the stored jobs.
        max_jobs: how many may be stored.
        owner: the new job's client address, or None.
        max_per_owner: how many unfinished jobs one client may have.

    Returns:
        ``(ids to evict first, refusal)``: refusal None when it fits, ``"full"`` when every
        stored job is queued or running, ``"owner"`` when ``owner`` already has
        ``max_per_owner`` unfinished jobs (one client cannot take the whole store or queue).
    """
    jobs = list(jobs)
    if owner is not None and sum(1 for j in jobs if j.owner == owner and not j.done
                                 ) >= max_per_owner:
        return [], "owner"
    excess = len(jobs) + 1 - max_jobs
    if excess <= 0:
        return [], None
    finished = sorted((j for j in jobs if j.done), key=lambda j: j.finished_at or 0.0)
    if len(finished) < excess:
        return [], "full"
    return [j.id for j in finished[:excess]], None


FIELDS = tuple(f.name for f in dataclasses.fields(Job) if f.name != "result")
"""The fields of a job record that travel between processes (the result stays put)."""


def job_fields(job: Job) -> dict[str, Any]:
    """The record of a job as a dict.

    Args:
        job: the job.

    Returns:
        Its :data:`FIELDS` (``Job(**job_fields(job))`` rebuilds it, without its result).
    """
    return {name: getattr(job, name) for name in FIELDS}


def count_states(jobs: Any) -> dict[str, int]:
    """Number of jobs per state.

    Args:
        jobs: an iterable of :class:`Job`.

    Returns:
        State -> count, every one of :data:`STATES` present.
    """
    out = dict.fromkeys(STATES, 0)
    for job in jobs:
        out[job.status] += 1
    return out
