"""What the operations report: progress stages, their wall time, and the typed reports.

Every operation reports its progress as ``progress(stage, fraction)`` with the stages
validate, assemble, factorize, solve and refine, and its report's ``timings`` in one shape:
stage -> seconds spent in it (:class:`Stages`). Each result carries a report dataclass
(:class:`ReconstructReport`, :class:`DeformReport`, :class:`ParameterizeReport`), read by
attribute or like a dict (``report["timings"]``) and serialized by :meth:`Report.to_dict`
(absent sections left out).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .core.budget import Budget
from .core.serialization import JsonDataclass, to_jsonable

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

    def part(self, stage: str, low: float = 0.0, high: float = 1.0,
             ) -> Callable[[float], None]:
        """``fraction -> self(stage, low + fraction * (high - low))``: the progress of a
        step that spans ``[low, high]`` of ``stage`` (an iterative solve's CG).

        Example:
            >>> seen = []
            >>> Stages(lambda stage, fraction: seen.append((stage, fraction))).part(
            ...     "solve", 0.5)(0.5)
            >>> seen
            [('solve', 0.75)]
        """
        return lambda fraction: self(stage, low + fraction * (high - low))

    def lap(self, stage: str) -> None:
        """Count the time since the last lap (or the start) towards ``stage``."""
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + now - self._clock
        self._clock = now

    def budget(self, max_seconds: float | None) -> Budget:
        """The operation's :class:`~solver.core.budget.Budget` of ``max_seconds`` (None: no
        limit), counted from its start."""
        return Budget(max_seconds, self.started)

    def left(self, max_seconds: float | None) -> float | None:
        """Seconds left (at least 0) of a budget of ``max_seconds`` from the start (None: no
        budget): :meth:`budget`'s :meth:`~solver.core.budget.Budget.left`."""
        return self.budget(max_seconds).left()


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
    from .core.validation import as_points
    from .mesh.manifold import manifold_topology

    points = as_points(vertices, "vertices")
    cut, topology = manifold_topology(faces, points)  # a non-manifold mesh: as its cut
    edges = np.unique(np.sort(cut.vertex_map[topology.edges], axis=1), axis=0)
    lengths = np.linalg.norm(points[edges[:, 1]] - points[edges[:, 0]], axis=1)
    report: dict[str, Any] = {
        "n_vertices": len(points), "n_faces": len(topology.faces), "n_edges": len(edges),
        "bounds": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
        "mean_edge_length": float(lengths.mean()) if len(lengths) else 0.0}
    if not cut.is_identity:
        report["input"] = cut.sections()
    return points, cut.vertex_map[topology.faces], report


Timings = dict[str, float]
"""Stage (validate, assemble, factorize, solve, refine) -> seconds."""


class Report(JsonDataclass, Mapping[str, Any]):
    """Base of the reports: dataclass fields that also read like a dict's keys; a field
    that is None is an absent section (not a key, left out of :meth:`to_dict`)."""

    def __getitem__(self, key: str) -> Any:
        value = getattr(self, key, None) if key in self._names() else None
        if value is None:
            raise KeyError(key)
        return value

    def __setitem__(self, key: str, value: Any) -> None:
        if key not in self._names():
            raise KeyError(f"{type(self).__name__} has no section {key!r}")
        setattr(self, key, value)

    def __iter__(self) -> Iterator[str]:
        return (name for name in self._names() if getattr(self, name) is not None)

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data: the present sections (:func:`solver.core.serialization.to_jsonable`)."""
        return {name: to_jsonable(getattr(self, name)) for name in self}

    @classmethod
    def _names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))  # type: ignore[arg-type]


@dataclasses.dataclass(eq=False)
class ReconstructReport(Report):
    """The report of :func:`solver.reconstruct`.

    Attributes:
        energy: residual energy per term of the returned unknowns (normalized units).
        first_solve_energy: the same of the first solve (before the orthonormalization).
        frame_orthonormality_error: max_t ||f_t^T f_t - I||_max of the first solve.
        orthonormalized: whether the second solve of Sec. 4 ran.
        refinement: whether and how it refined (:meth:`solver.refine.Refiner.run`).
        timings: seconds per stage.
        backend, analysis: the factorization's backend and analysis ("none": no
            factorization).
        solve_path: "tree-integration", "factorization" or "iterative".
        linear_solver: how Eq. 5 was solved (None: tree integration): ``{"method":
            "direct", "backend"}`` or ``{"method": "iterative", "iterations",
            "relative_residual", "tolerance", "converged", ...}``
            (:class:`solver.linalg.iterative.IterativeStats`).
        n_unknowns: N = n + 3 m.
        frame_weight, weighting, length_scale: the energy's.
        regularized_components: components whose gauge a reference embedding fixed.
        anchored_components: ``{"component", "vertex", "face"}`` of each anchored one.
        isolated_vertices: vertices in no face.
        integrability: the integrability summary (None: not checked).
        vjp: :func:`solver.reconstruct_vjp`'s preparation (None otherwise).
        warnings: thresholds the answer is past (:mod:`solver.core.warnings`; [] when none).
        input: what was done to the input to solve it (``wrapped_angles``: angles given
            outside (-pi, pi] and wrapped; ``zero_area_faces``: faces whose lengths give
            zero area, laid out as segments, :func:`solver.mesh.forms.flat_faces`; a
            non-manifold mesh's cut, see :mod:`solver.mesh.manifold`).
    """

    energy: dict[str, float]
    first_solve_energy: dict[str, float]
    frame_orthonormality_error: float
    orthonormalized: bool
    refinement: dict[str, Any]
    timings: Timings
    backend: str
    analysis: str
    solve_path: str
    n_unknowns: int
    frame_weight: float
    weighting: str
    length_scale: float
    regularized_components: list[int]
    anchored_components: list[dict[str, int]]
    isolated_vertices: list[int]
    integrability: dict[str, Any] | None = None
    vjp: dict[str, Any] | None = None
    warnings: list[dict[str, Any]] | None = None
    input: dict[str, Any] | None = None
    linear_solver: dict[str, Any] | None = None


@dataclasses.dataclass(eq=False)
class DeformReport(Report):
    """The report of :func:`solver.deform`.

    Attributes:
        timings: seconds per stage.
        backend, analysis: the factorization's.
        n_unknowns: unknowns of the ROI's system.
        roi_faces: faces of the system (those touching the region of interest).
        orthonormalized: whether the second solve of Sec. 4 ran.
        refinement: whether and how it refined.
        distortion: :func:`solver.mesh.metrics.distortion` against the rest mesh (compact).
        warnings: thresholds the answer is past (:mod:`solver.core.warnings`; [] when none).
        input: what was done to the input (``cut``: a non-manifold mesh's manifold cut,
            :mod:`solver.mesh.manifold`, with the spread of the copies; ``zero_area_faces``: rest
            faces with collinear corners, whose normals follow
            :func:`solver.mesh.forms.degenerate_normals`); None: nothing.
        linear_solver: how Eq. 5 was solved (``options.linear_solver``): ``{"method":
            "direct", "backend"}`` or ``{"method": "iterative", "iterations", ...}``, as in
            :class:`ReconstructReport` (the refinement's steps: ``refinement.linear_solver``).
    """

    timings: Timings
    backend: str
    analysis: str
    n_unknowns: int
    roi_faces: int
    orthonormalized: bool
    refinement: dict[str, Any]
    distortion: dict[str, Any]
    warnings: list[dict[str, Any]] | None = None
    input: dict[str, Any] | None = None
    linear_solver: dict[str, Any] | None = None


@dataclasses.dataclass(eq=False)
class ParameterizeReport(Report):
    """The report of :func:`solver.parameterize`.

    Attributes:
        flipped_count: faces whose uv orientation is reversed.
        area_ratio_summary, angle_distortion_summary, length_change_summary: summaries
            (:func:`solver.mesh.metrics.summary`) of uv/3D area - 1, corner-angle change and
            relative edge-length change.
        angle_distortion_histogram, length_change_histogram: their histograms.
        planarity_error: max |z| of the linear answer (0 in exact arithmetic).
        orthonormalized: whether the second solve ran.
        refinement: whether and how it refined.
        anchored_components: ``{"component", "vertex", "face"}`` of each component.
        backend, analysis: the factorization's.
        timings: seconds per stage.
        warnings: thresholds the answer is past (:mod:`solver.core.warnings`; [] when none).
        input: what was done to the input (``cut``: a non-manifold mesh's manifold cut,
            :mod:`solver.mesh.manifold`: a cut vertex is one more uv index; ``zero_area_faces``:
            faces with collinear corners); None: nothing.
        atlas: ``charts``, ``seam_edges``, ``seam_length`` (input units),
            ``packing_efficiency`` (fraction of the unit square covered), ``padding``
            (fraction of the side) and ``padding_texels`` at ``atlas_texels``, ``uv_count``,
            ``boundary_crossings`` (one chart: boundary-edge pairs crossing in uv, None past
            20 000 boundary edges; an atlas: 0, each chart checked).
    """

    flipped_count: int
    area_ratio_summary: dict[str, float]
    angle_distortion_summary: dict[str, float]
    length_change_summary: dict[str, float]
    angle_distortion_histogram: dict[str, Any]
    length_change_histogram: dict[str, Any]
    planarity_error: float
    orthonormalized: bool
    refinement: dict[str, Any]
    anchored_components: list[dict[str, int]]
    backend: str
    analysis: str
    timings: Timings
    warnings: list[dict[str, Any]] | None = None
    input: dict[str, Any] | None = None
    atlas: dict[str, Any] | None = None
