"""What the operations measure while they run: progress stages and their wall time.

Every operation reports its progress as ``progress(stage, fraction)`` with the stages
validate, assemble, factorize, solve and refine, and its report's ``timings`` in one shape:
stage -> seconds spent in it (:class:`Stages`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

Progress = Callable[[str, float], None]
"""``progress(stage, fraction)``: a stage (validate, assemble, factorize, solve, refine)
and how far it is, 0 to 1."""


class Stages:
    """Tells ``progress`` where an operation is and times its stages.

    Example:
        >>> seen = []
        >>> stages = Stages(lambda stage, fraction: seen.append((stage, fraction)))
        >>> stages("validate")
        >>> stages.lap("validate")
        >>> seen, sorted(stages.timings)
        ([('validate', 0.0)], ['validate'])
    """

    def __init__(self, progress: Progress | None = None) -> None:
        self.progress = progress
        self.timings: dict[str, float] = {}
        """Stage -> seconds spent in it (added up when a stage comes back)."""
        self.started = self._clock = time.perf_counter()

    def __call__(self, stage: str, fraction: float = 0.0) -> None:
        """Report ``fraction`` (0 to 1) of ``stage`` to the progress callback, if any."""
        if self.progress is not None:
            self.progress(stage, fraction)

    def lap(self, stage: str) -> None:
        """Count the time since the last lap (or the start) towards ``stage``."""
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + now - self._clock
        self._clock = now

    def left(self, max_seconds: float | None) -> float | None:
        """Seconds left of a budget of ``max_seconds`` from the start (None: no budget)."""
        return None if max_seconds is None else max_seconds - (time.perf_counter()
                                                               - self.started)


def mesh_summary(vertices: ArrayLike, faces: ArrayLike,
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """A mesh checked the way every operation checks it (finite points, index range,
    manifoldness, orientation) and its summary.

    Args:
        vertices: (n, 3) float positions.
        faces: (m, 3) int.
    Returns:
        ``(vertices, faces, report)``: (n, 3) float64, (m, 3) int64 and ``n_vertices``,
        ``n_faces``, ``n_edges``, ``bounds`` (min and max corner) and ``mean_edge_length``.

    Example:
        >>> _, _, report = mesh_summary([[0, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 1, 2]])
        >>> report["n_edges"], report["bounds"]
        (3, [[0.0, 0.0, 0.0], [2.0, 1.0, 0.0]])
    """
    from .topology import build_topology
    from .validation import as_points

    points = as_points(vertices, "vertices")
    topology = build_topology(faces, n_vertices=len(points))
    edges = topology.edges
    lengths = np.linalg.norm(points[edges[:, 1]] - points[edges[:, 0]], axis=1)
    report = {"n_vertices": len(points), "n_faces": len(topology.faces), "n_edges": len(edges),
              "bounds": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
              "mean_edge_length": float(lengths.mean()) if len(lengths) else 0.0}
    return points, np.asarray(topology.faces, dtype=np.int64), report
