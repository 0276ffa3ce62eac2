"""Atlas charts: cut a mesh into charts that flatten well and flatten each.

The seams come from :mod:`solver.mesh.charts`; each chart is flattened by
:func:`solver.chart_flattening.flatten_chart` and kept only when it passes the checks of
:func:`chart_layouts` (else it is bisected). :func:`assemble` concatenates the accepted
charts' layouts over uv indices of their own (a seam vertex once per chart).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .atlas_rules import ATLAS_RULES
from .chart_flattening import (
    DEVELOPABLE,
    ChartFlattening,
    flatten_chart,
    local_global_flattening,
    refine_chart,
    relative_length_change,
    tutte_embedding,
    uv_edges,
)
from .mesh.charts import (
    ChartMesh,
    bisect,
    chart_mesh,
    connected_face_sets,
    disk_like_components,
    dual_graph,
    is_disk_like,
    labelled_face_sets,
    xatlas_charts,
)
from .mesh.forms import zero_area_faces
from .mesh.frames import triangle_layouts
from .mesh.packing import boundary_crossings, folded, positive_loops
from .mesh.topology import MeshTopology, build_topology
from .options import ParameterizeOptions
from .reconstruct import Progress
from .refine.form_energy import FORMS_TOLERANCE
from .refine.outcomes import not_refined, with_outcome
from .reports import Stages


@dataclass
class ChartLayout:
    """An accepted chart: its mesh (:class:`solver.mesh.charts.ChartMesh`) and flattening."""

    mesh: ChartMesh
    flattening: ChartFlattening


def chart_layouts(V: np.ndarray, topology: MeshTopology, angles: np.ndarray,
                  opts: ParameterizeOptions, stages: Stages,
                  progress: Progress | None = None, *, seeds: str = "xatlas",
                  ) -> list[ChartLayout]:
    """Cut the mesh into charts and flatten each (the seams of :mod:`solver.mesh.charts`).

    Starting from ``seeds`` (``"xatlas"``: xatlas's charts,
    :func:`solver.mesh.charts.xatlas_charts`, each edge-connected piece one chart;
    ``"components"``: the edge-connected components, the bisection alone), a chart is
    bisected while it is closed or has a handle, while its linear flattening's mean
    relative length change is above twice ``opts.max_chart_distortion``, or while its
    refined flattening is above it, has a flipped face or overlaps itself
    (:func:`overlaps_itself`).

    The charts waiting are flattened in rounds (:func:`_flatten_round`: the linear
    flattening and the refinement's start solved once for the disjoint union of their
    meshes, each chart then refined and checked alone), and the parts of those that fail
    wait for the next round.
    Once ``opts.max_seconds`` is spent, the charts left are flattened one at a time and each
    is kept (:func:`_flatten_or_none`). ``progress("charts", fraction of faces placed)``.
    """
    faces = topology.faces
    m = len(faces)
    graph = dual_graph(V, topology, angles, opts.crease_weight)
    if seeds == "xatlas":
        queue = labelled_face_sets(graph, xatlas_charts(V, faces))
    else:
        queue = connected_face_sets(graph, np.arange(m), m)
    quiet = Stages(None)
    done: list[ChartLayout] = []
    placed = 0

    def keep(chart: ChartLayout) -> None:
        """Accept a chart; progress: the fraction of faces placed, chart by chart."""
        nonlocal placed
        done.append(chart)
        placed += len(chart.mesh.face_ids)
        stages("charts", placed / m)

    while queue:
        if _out_of_time(stages, opts):
            ids = queue.pop()
            chart = chart_mesh(faces, ids)
            flattening = _flatten_or_none(V[chart.vertex_ids], chart.faces,
                                          chart_options(opts, len(ids)), quiet,
                                          out_of_time=True)
            failed = [ids] if flattening is None else []
            if flattening is not None:
                keep(ChartLayout(chart, flattening))
        else:
            failed = _flatten_round(V, faces, queue, opts, quiet, keep)
            queue = []
        for ids in failed:
            queue.extend(bisect(graph, ids, m))
    for stage, seconds in quiet.timings.items():
        stages.timings[stage] = stages.timings.get(stage, 0.0) + seconds
    return done


@dataclass
class _Union:
    """Charts as one mesh: their vertices and faces concatenated (chart ``k``'s vertex ``i``
    is ``offsets[k] + i``), its topology and edge lengths; ``source`` the mesh's (n, 3)
    vertices the charts index."""

    source: np.ndarray
    charts: list[ChartMesh]
    vertices: np.ndarray
    topology: MeshTopology
    lengths: np.ndarray
    offsets: np.ndarray
    vertex_chart: np.ndarray

    @classmethod
    def of(cls, V: np.ndarray, charts: list[ChartMesh]) -> _Union:
        sizes = np.array([len(chart.vertex_ids) for chart in charts])
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        vertices = V[np.concatenate([chart.vertex_ids for chart in charts])]
        faces = np.concatenate([chart.faces + offsets[k] for k, chart in enumerate(charts)])
        topology = build_topology(faces, n_vertices=len(vertices))
        return cls(V, charts, vertices, topology, _lengths(vertices, topology), offsets,
                   np.repeat(np.arange(len(charts)), sizes))

    def part(self, uv: np.ndarray, k: int) -> np.ndarray:
        """Chart ``k``'s rows of ``uv`` (a copy)."""
        return np.array(uv[self.offsets[k]:self.offsets[k + 1]])

    def disk_like(self) -> np.ndarray:
        """(charts,) bool: each chart :func:`~solver.mesh.charts.is_disk_like` (a chart is
        one component of the union)."""
        t = self.topology
        return disk_like_components(t)[t.vertex_component[self.offsets[:-1]]]

    def length_change(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(charts,) each chart's mean and (charts,) largest absolute relative edge-length
        change of ``uv`` (:func:`mean_length_change`, over its edges)."""
        faces = self.topology.faces
        change = np.abs(relative_length_change(self.vertices, uv, faces,
                                               np.arange(len(self.vertices))))
        chart = self.vertex_chart[uv_edges(faces)[:, 0]]
        count = len(self.charts)
        largest = np.zeros(count)
        np.maximum.at(largest, chart, change)
        return np.bincount(chart, change, count) / np.bincount(chart, minlength=count), largest

    def exact_hinges(self, uv: np.ndarray, largest: np.ndarray) -> np.ndarray:
        """(charts,) bool: the chart is two faces (a hinge), neither of zero area in 3D nor
        folded in ``uv``, whose edge lengths ``uv`` keeps (``largest`` (charts,) relative
        change at most :data:`~solver.refine.form_energy.FORMS_TOLERANCE`): then it is
        exact and cannot overlap itself (two unfolded triangles lie on either side of
        their shared edge), so no refinement or check of its own is needed."""
        faces = self.topology.faces
        count = len(self.charts)
        face_chart = self.vertex_chart[faces[:, 0]]
        flat = zero_area_faces(self.vertices, faces)
        spoilt = np.zeros(len(faces), dtype=bool)
        spoilt[flat] = True
        spoilt |= folded(uv, faces, flat)
        return ((np.bincount(face_chart, minlength=count) == 2) & (largest <= FORMS_TOLERANCE)
                & (np.bincount(face_chart, spoilt, count) == 0))

    def narrowed(self, keep: np.ndarray) -> _Union:
        """The union of the charts where ``keep`` (this union itself when that is all)."""
        if keep.all():
            return self
        return _Union.of(self.source,
                         [chart for chart, ok in zip(self.charts, keep, strict=True) if ok])


def _flatten_round(V: np.ndarray, faces: np.ndarray, queue: list[np.ndarray],
                   opts: ParameterizeOptions, stages: Stages,
                   keep: Callable[[ChartLayout], None]) -> list[np.ndarray]:
    """Flatten the charts ``queue`` (each (k,) mesh face indices) as :func:`_flatten_or_none`
    flattens each, with the solves that need no iteration done for all at once: one linear
    flattening of their union (the quick check: within twice ``opts.max_chart_distortion``)
    and one Tutte embedding and local/global fit of the union of those that pass (the
    refinement's start). Each chart is then refined and checked alone, so its stopping rules
    and checks are its own. Each accepted chart is handed to ``keep`` as soon as it is;
    returns the face sets to bisect."""
    failed: list[np.ndarray] = []
    single = np.array([ids[0] for ids in queue if len(ids) == 1], dtype=np.int64)
    for chart in _single_faces(V, faces, single):
        keep(chart)
    several = [(ids, chart_mesh(faces, ids)) for ids in queue if len(ids) > 1]
    if not several:
        return failed
    union = _Union.of(V, [chart for _, chart in several])
    disk = union.disk_like()
    several, rejected = _split(several, disk)
    failed += rejected
    if not several:
        return failed
    union = union.narrowed(disk)
    options = chart_options(opts, len(union.topology.faces))
    quick = flatten_chart(union.vertices, union.topology, union.lengths, options, stages,
                          refine=False)
    mean, largest = union.length_change(quick.uv)
    close = mean <= 2 * opts.max_chart_distortion
    linear = [union.part(quick.uv, k) for k in np.flatnonzero(close)]
    hinged = union.exact_hinges(quick.uv, largest)[close]
    several, rejected = _split(several, close)
    failed += rejected
    if not several:
        return failed
    starts: dict[int, tuple[np.ndarray, str]] = {}
    if opts.refine is not False:
        starts = _starts(union.narrowed(close), largest[close] > FORMS_TOLERANCE, options)
    for k, (ids, chart) in enumerate(several):
        flattening = _part(quick, linear[k])
        if hinged[k]:   # what refine_chart and _acceptable would find, without a topology
            if opts.refine is not False:
                flattening.refinement = not_refined(DEVELOPABLE)
            keep(ChartLayout(chart, flattening))
            continue
        Vc = V[chart.vertex_ids]
        topology = build_topology(chart.faces, n_vertices=len(Vc))
        if opts.refine is not False:
            flattening = refine_chart(Vc, topology, _lengths(Vc, topology),
                                      chart_options(opts, len(ids)), stages, flattening,
                                      start=starts.get(k))
        if _acceptable(Vc, flattening.uv, topology, opts.max_chart_distortion):
            keep(ChartLayout(chart, flattening))
        else:
            failed.append(ids)
    return failed


def _split(pairs: list[Any], keep: np.ndarray) -> tuple[list[Any], list[np.ndarray]]:
    """``(ids, chart)`` pairs where ``keep``, and the face sets of the others."""
    return ([pair for pair, ok in zip(pairs, keep, strict=True) if ok],
            [pair[0] for pair, ok in zip(pairs, keep, strict=True) if not ok])


def _starts(union: _Union, needed: np.ndarray, opts: ParameterizeOptions,
            ) -> dict[int, tuple[np.ndarray, str]]:
    """The refinement's start of each chart of ``union`` (by its index) where ``needed``
    (its linear flattening does not already keep its edge lengths), as
    :func:`solver.chart_flattening.refine_chart` would make it (local/global steps from a
    Tutte embedding), for all of them by one solve of each; {} without a Tutte embedding
    (refine_chart then starts each chart its own way)."""
    if not needed.any():
        return {}
    union = union.narrowed(needed)
    backend = opts.backend or "auto"
    tutte = tutte_embedding(union.vertices, union.topology, union.lengths, backend)
    if tutte is None:
        return {}
    fitted = local_global_flattening(union.topology, union.lengths, tutte, backend=backend)
    return {int(k): (union.part(fitted, i), "local/global from Tutte")
            for i, k in enumerate(np.flatnonzero(needed))}


def _part(flattening: ChartFlattening, uv: np.ndarray) -> ChartFlattening:
    """A chart's share of a flattening of several charts: its ``uv``, the rest shared."""
    return ChartFlattening(uv, flattening.backend, flattening.analysis, flattening.planarity,
                           flattening.refinement, [])


def _acceptable(V: np.ndarray, uv: np.ndarray, topology: MeshTopology, limit: float) -> bool:
    """Whether a chart's flattening ``uv`` stands: no flipped face, a mean relative length
    change of at most ``limit``, no overlap with itself (:func:`overlaps_itself`)."""
    faces = topology.faces
    flat = zero_area_faces(V, faces)
    return not (folded(uv, faces, flat).any() or mean_length_change(V, uv, faces) > limit
                or overlaps_itself(uv, faces, topology.boundary_loops, flat))


def _out_of_time(stages: Stages, opts: ParameterizeOptions) -> bool:
    left = stages.left(opts.max_seconds)
    return left is not None and left <= 0


def _flatten_or_none(V: np.ndarray, faces: np.ndarray, opts: ParameterizeOptions,
                     stages: Stages, *, out_of_time: bool) -> ChartFlattening | None:
    """The chart's flattening, or None when it is to be split (see :func:`chart_layouts`);
    a single face, or any chart once the time is out, is always kept."""
    if len(faces) == 1:
        return _single_faces(V, faces, np.zeros(1, dtype=np.int64))[0].flattening
    topology = build_topology(faces, n_vertices=len(V))
    if not is_disk_like(topology):
        return None if not out_of_time else _last_resort(V, topology, opts, stages)
    lengths = _lengths(V, topology)
    limit = opts.max_chart_distortion
    quick = flatten_chart(V, topology, lengths, opts, stages, refine=False)
    if not out_of_time and mean_length_change(V, quick.uv, faces) > 2 * limit:
        return None
    full = quick if opts.refine is False else refine_chart(V, topology, lengths, opts, stages,
                                                            quick)
    if out_of_time or _acceptable(V, full.uv, topology, limit):
        return full
    return None


def _single_faces(V: np.ndarray, faces: np.ndarray, face_ids: np.ndarray,
                  ) -> list[ChartLayout]:
    """Each face of ``face_ids`` (k,) int64 as a chart of its own, laid out with its edge
    lengths (no solve; a face whose lengths violate the triangle inequality lies flat), all
    at once: the charts :func:`solver.mesh.charts.chart_mesh` makes of them (chart vertices
    in the order of their mesh vertices) with their layouts."""
    if not len(face_ids):
        return []
    corners = faces[face_ids]                                           # (k, 3)
    sides = np.linalg.norm(V[np.roll(corners, -1, axis=1)] - V[corners], axis=2)
    layouts = triangle_layouts(sides, check=False)                     # (k, 3, 2) per corner
    order = np.argsort(corners, axis=1, kind="stable")                  # chart vertex -> corner
    rank = np.argsort(order, axis=1)                                    # corner -> chart vertex
    uv = np.take_along_axis(layouts, order[:, :, None], axis=1)        # per chart vertex
    vertex_ids = np.take_along_axis(corners, order, axis=1)
    return [ChartLayout(ChartMesh(face_ids[i:i + 1], vertex_ids[i], rank[i:i + 1]),
                        ChartFlattening(uv[i], "none", "", 0.0,
                                        {"refined": False, "reason": "one face"}, []))
            for i in range(len(face_ids))]


def _last_resort(V: np.ndarray, topology: MeshTopology, opts: ParameterizeOptions,
                 stages: Stages) -> ChartFlattening | None:
    """Out of time with a closed chart: it must still be cut (None) unless it is open."""
    if any(c["closed"] for c in topology.component_summary()):
        return None
    return flatten_chart(V, topology, _lengths(V, topology), opts, stages, refine=False)


def _lengths(V: np.ndarray, topology: MeshTopology) -> np.ndarray:
    return np.linalg.norm(V[topology.edges[:, 1]] - V[topology.edges[:, 0]], axis=1)


def mean_length_change(V: np.ndarray, uv: np.ndarray, faces: np.ndarray) -> float:
    identity = np.arange(len(V))
    return float(np.abs(relative_length_change(V, uv, faces, identity)).mean())


def overlaps_itself(uv: np.ndarray, faces: np.ndarray, loops: list[np.ndarray],
                    zero_area: np.ndarray | None = None) -> bool:
    """Whether a chart's layout ``uv`` (n, 2) over ``faces`` (m, 3) with boundary ``loops``
    covers some point twice: a flipped face (:func:`solver.mesh.packing.folded`; ``zero_area``
    faces, flat in 3D, never count), boundary edges that cross
    (:func:`solver.mesh.packing.boundary_crossings`), or a hole laid out inside out (more than
    one counter-clockwise loop, :func:`solver.mesh.packing.positive_loops`). Without any of
    these the layout is injective."""
    return bool(folded(uv, faces, zero_area).any()) or positive_loops(uv, loops) > 1 \
        or boundary_crossings(uv, faces) > 0


def chart_options(opts: ParameterizeOptions, faces: int) -> ParameterizeOptions:
    if (opts.backend or "auto") == "auto" and faces < ATLAS_RULES.small_chart_faces:
        return opts.replace(backend="superlu")
    return opts



def assemble(charts: list[ChartLayout], m: int,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate the charts: layout (k, 2), uv_faces (m, 3), uv_vertex (k,),
    face_chart (m,). A loop over charts."""
    uv_faces = np.zeros((m, 3), dtype=np.int64)
    face_chart = np.zeros(m, dtype=np.int64)
    layouts, vertex_ids, offset = [], [], 0
    for index, chart in enumerate(charts):
        uv_faces[chart.mesh.face_ids] = chart.mesh.faces + offset
        face_chart[chart.mesh.face_ids] = index
        layouts.append(chart.flattening.uv)
        vertex_ids.append(chart.mesh.vertex_ids)
        offset += len(chart.mesh.vertex_ids)
    return (np.concatenate(layouts), uv_faces, np.concatenate(vertex_ids), face_chart)



__all__ = [
    "ChartLayout",
    "assemble",
    "chart_layouts",
    "chart_options",
    "mean_length_change",
]


def atlas_refinement(charts: list[ChartLayout]) -> dict[str, Any]:
    """The refinement report of an atlas: its charts' refinements told as one.

    ``refined``: some chart was refined; ``converged``: every refined chart converged;
    ``iterations``: their sum; ``stop_reason``: ``"converged"``, or the stop reason of the
    largest chart that did not converge; ``energy_before``/``energy_after``: sums over the
    refined charts; ``charts``, ``charts_refined``, ``charts_unconverged``: counts. Its
    ``outcome`` and ``outcome_text`` (:mod:`solver.refine.outcomes`) then say what the
    charts did, with the counts in words ("converged after 48 iterations (15 of 15 charts
    refined)"); a chart that needed no refinement (developable, one face) is not refined.
    An atlas with no refined chart gives the reason of its largest chart; one whose charts
    made no progress (a time limit) says "not refined" with the chart count alone.
    """
    reports = [chart.flattening.refinement for chart in charts]
    sizes = [len(chart.mesh.face_ids) for chart in charts]
    ran = [(size, r) for size, r in zip(sizes, reports, strict=True) if r.get("refined")]
    if not ran:
        largest = reports[int(np.argmax(sizes))] if reports else {}
        report = with_outcome({"refined": False, "reason": largest.get("reason", "not run"),
                               "charts": len(charts), "charts_refined": 0,
                               "charts_unconverged": 0})
        report["outcome_text"] += f" ({len(charts)} charts)"
        return report
    unconverged = [(size, r) for size, r in ran if not r.get("converged")]
    report: dict[str, Any] = {
        "refined": True, "converged": not unconverged,
        "stop_reason": (max(unconverged, key=lambda pair: pair[0])[1].get("stop_reason")
                        if unconverged else "converged"),
        "iterations": sum(int(r.get("iterations") or 0) for _, r in ran),
        "charts": len(charts), "charts_refined": len(ran),
        "charts_unconverged": len(unconverged)}
    if all(r.get("energy_before") is not None and r.get("energy_after") is not None
           for _, r in ran):
        report["energy_before"] = float(sum(r["energy_before"] for _, r in ran))
        report["energy_after"] = float(sum(r["energy_after"] for _, r in ran))
    report = with_outcome(report)
    counts = f"{len(ran)} of {len(charts)} charts refined"
    if report["outcome"] == "not-refined":  # no chart made progress (a time limit)
        counts = f"{len(charts)} charts"
    elif unconverged:
        counts += f", {len(unconverged)} not converged"
    report["outcome_text"] += f" ({counts})"
    return report
