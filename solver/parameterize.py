"""Quasi-isometric parameterization (Sec. 5) of any manifold mesh.

One chart where the mesh flattens well as one (today's layout), else an atlas: charts cut
along seams (:mod:`solver.atlas`), each flattened by :mod:`solver.chart_flattening`, packed
into the unit square (:mod:`solver.mesh.packing`). This module measures and reports the answer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from .atlas import (
    ChartLayout,
    assemble,
    atlas_refinement,
    chart_layouts,
    mean_length_change,
    overlaps_itself,
)
from .atlas_rules import ATLAS_RULES
from .chart_flattening import ChartFlattening, flatten_chart, relative_length_change
from .core.errors import DegenerateFaceError, TopologyError
from .core.serialization import JsonDataclass
from .core.validation import as_points
from .core.warnings import (
    as_report,
    flattening_warnings,
)
from .mesh.charts import is_disk_like, seam_edges
from .mesh.forms import fundamental_forms, zero_area_faces
from .mesh.manifold import ManifoldCut, manifold_topology
from .mesh.metrics import corner_angles, histogram, summary
from .mesh.packing import (
    Packed,
    PackingRules,
    boundary_crossings,
    folded,
    pack_charts,
    packing_efficiency,
    signed_areas,
)
from .mesh.topology import MeshTopology, build_topology
from .options import ParameterizeOptions
from .reconstruct import Progress
from .refine.outcomes import stalled_at_targets
from .reports import ParameterizeReport, Stages


@dataclass
class Parameterization(JsonDataclass):
    """Result of :func:`parameterize`.

    With one chart the uv indices are the file's vertices (``uv`` (n, 2), ``uv_faces`` the
    faces, ``uv_vertex`` the identity); with seams a seam vertex has one uv index per chart
    it borders.

    Attributes:
        uv: (k, 2) float64 the flat layout in the input's units (charts packed apart).
        flipped_faces: (f,) int64 faces whose uv orientation is reversed.
        area_ratio: (m,) float64 uv area / 3D area.
        angle_distortion: (m,) float64 max |corner angle change| per face (radians).
        report: :class:`solver.reports.ParameterizeReport` (summaries, histograms,
            timings, backend, components, ``atlas``, ``warnings``).
        texcoords: (k, 2) float64 the layout packed into the unit square (texture
            coordinates; ``uv`` is ``texcoords`` times one scale).
        uv_faces: (m, 3) int64 each face's uv indices.
        uv_vertex: (k,) int64 the file vertex of each uv index.
        face_chart: (m,) int64 the chart of each face.
    """

    uv: np.ndarray
    flipped_faces: np.ndarray
    area_ratio: np.ndarray
    angle_distortion: np.ndarray
    report: ParameterizeReport
    texcoords: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    uv_vertex: np.ndarray | None = None
    face_chart: np.ndarray | None = None

    _array_fields: ClassVar[dict[str, Any]] = {
        "uv": np.float64, "flipped_faces": np.int64, "area_ratio": np.float64,
        "angle_distortion": np.float64, "texcoords": np.float64, "uv_faces": np.int64,
        "uv_vertex": np.int64, "face_chart": np.int64,
    }
    _nested_fields: ClassVar[dict[str, Any]] = {"report": ParameterizeReport}


def parameterize(vertices: ArrayLike, faces: ArrayLike, *,
                 options: ParameterizeOptions | None = None,
                 progress: Progress | None = None, **overrides: Any) -> Parameterization:
    """Flatten a mesh: one chart where that flattens well, else charts cut apart by seams
    and packed into the unit square (an atlas).

    With ``seams="auto"`` (default) a mesh that is one component with a boundary is first
    flattened as one chart (today's layout, unchanged); it is kept when it is disk-like
    (genus 0), has at most 0.1% flipped faces, does not overlap itself where it has none,
    and its mean relative length change is at most twice ``max_chart_distortion``.
    Otherwise (closed surfaces, handles, several parts, too much distortion)
    :func:`chart_layouts` cuts it into charts, each flattened by the same method, and
    :func:`solver.mesh.packing.pack_charts` packs them. ``seams="none"``: one chart per
    component as before (a closed component is refused).

    Args:
        vertices: (n, 3) float.
        faces: (m, 3) int, counter-clockwise.
        options: :class:`solver.options.ParameterizeOptions` (``orthonormalize`` defaults
            to True here: the second solve with planar-rotation frame targets).
            ``refine`` None (default) or True fits the edge lengths in the plane
            nonlinearly from the linear answer (:mod:`solver.refine` with ``dim=2``: lengths
            and signed areas, so flipped faces are pushed back), unless the linear answer
            already has every length (a developable surface); False: the linear answer.
            ``max_seconds`` budgets the whole call.
        progress: optional ``progress(stage, fraction)`` (validate ... refine; ``charts``
            with the fraction of faces placed when cutting).
        **overrides: fields of ``options`` given as keywords.

    Returns:
        :class:`Parameterization`: the layout ``uv`` (k, 2) over ``uv_faces``, unit-square
        ``texcoords``, ``uv_vertex`` (file vertex of each uv index), ``face_chart``,
        flipped faces, per-face distortion and a report (summaries, histograms, atlas,
        warnings, ``timings`` per stage, backend).

    Raises:
        TopologyError: ``seams="none"`` and a component without boundary.

    Example:
        >>> import numpy as np
        >>> from solver import parameterize
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.2]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> flat = parameterize(V, F)                   # a low pyramid: one chart
        >>> flat.uv.shape, len(flat.flipped_faces), flat.report.atlas["charts"]
        ((5, 2), 0, 1)
    """
    opts = ParameterizeOptions.given(options, overrides)
    # A seam of vertices at one position is the user's cut here: kept open.
    cut = manifold_topology(faces, as_points(vertices, "vertices"), coincident=False)[0]
    if not cut.is_identity:  # a non-manifold mesh: flattened on its cut (solver.mesh.manifold)
        return _on_file_vertices(parameterize(cut.to_cut(as_points(vertices, "vertices")),
                                              cut.faces, options=opts, progress=progress), cut)
    stages = Stages(progress)
    stages("validate")
    V = as_points(vertices, "vertices")
    topology = build_topology(faces, n_vertices=len(V))
    closed = [c["component"] for c in topology.component_summary() if c["closed"]]
    if closed and opts.seams == "none":
        raise TopologyError(
            f"component {closed[0]} is a closed surface: it has no boundary, so it cannot be "
            "flattened; cut it open along a seam (duplicate the seam vertices) first, or "
            "let seams='auto' cut it",
            field="faces", details={"closed_components": closed})
    forms = fundamental_forms(V, topology.faces, coincident=False)
    _refuse_no_area(V, topology.faces)
    stages.lap("validate")
    F = topology.faces
    if opts.seams == "none" or (topology.n_components == 1 and not closed):
        single = flatten_chart(V, topology, forms.lengths, opts, stages,
                               refine=opts.refine is not False, progress=progress)
        if opts.seams == "none" or _keeps_single_chart(V, single.uv, topology, opts):
            identity = np.arange(len(V))
            return _result(V, F, single.uv, F, identity, np.zeros(len(F), dtype=np.int64),
                           _single_texcoords(single.uv, topology), single, opts, stages,
                           forms, topology, scale=None)
    charts, packed, (_, uv_faces, uv_vertex, face_chart) = _packed_atlas(
        V, topology, forms.angles, opts, stages, progress)
    last = max(charts, key=lambda chart: len(chart.mesh.face_ids)).flattening
    summary_refinement = atlas_refinement(charts)
    combined = ChartFlattening(packed.texcoords * packed.scale, last.backend, last.analysis,
                               max(c.flattening.planarity for c in charts),
                               summary_refinement, [])
    return _result(V, F, combined.uv, uv_faces, uv_vertex, face_chart, packed.texcoords,
                   combined, opts, stages, forms, topology, scale=packed)


def _refuse_no_area(V: np.ndarray, F: np.ndarray) -> None:
    """Raise when every face has zero area (:func:`solver.mesh.forms.zero_area_faces`:
    collinear or coincident corners): such a mesh has nothing to lay out (CGAL's
    degeneracies/all_degen.off)."""
    if len(zero_area_faces(V, F)) == len(F):
        raise DegenerateFaceError(
            "every face has zero area (collinear or coincident corners): a mesh without "
            "area has no flattening", field="faces")


def _packed_atlas(V: np.ndarray, topology: MeshTopology, angles: np.ndarray,
                  opts: ParameterizeOptions, stages: Stages, progress: Progress | None,
                  ) -> tuple[list[ChartLayout], Packed, tuple[np.ndarray, ...]]:
    """Charts seeded by xatlas's charting, packed; when they pack below
    :attr:`~solver.atlas_rules.AtlasRules.rechart_below` (the torus 0.34, the koala 0.46)
    and time is left, the charts of the bisection alone (``seeds="components"``) are packed
    too and the atlas that packs better is kept. Returns the charts, the packing and
    :func:`assemble`'s arrays."""
    best = None
    for seeds in ("xatlas", "components"):
        if best is not None and (best[1].efficiency >= ATLAS_RULES.rechart_below
                                 or _out_of_time(stages, opts)):
            break
        charts = chart_layouts(V, topology, angles, opts, stages, progress, seeds=seeds)
        stages("pack")
        arrays = assemble(charts, len(topology.faces))
        packed = pack_charts(arrays[0], arrays[1], arrays[3])
        stages.lap("pack")
        if best is None or packed.efficiency > best[1].efficiency:
            best = (charts, packed, arrays)
    assert best is not None
    return best


def _out_of_time(stages: Stages, opts: ParameterizeOptions) -> bool:
    left = stages.left(opts.max_seconds)
    return left is not None and left <= 0


def _keeps_single_chart(V: np.ndarray, uv: np.ndarray, topology: MeshTopology,
                        opts: ParameterizeOptions) -> bool:
    """Whether today's single chart stands: a disk-like mesh whose flattening covers no
    point twice (no flipped face, no boundary crossing, no hole inside out:
    :func:`solver.atlas.overlaps_itself`) with a mean relative length change of at most
    twice ``max_chart_distortion`` (the bumpy plane's 0.052 stays one chart)."""
    F = topology.faces
    if not is_disk_like(topology):
        return False
    if mean_length_change(V, uv, F) > 2 * opts.max_chart_distortion:
        return False
    return not overlaps_itself(uv, F, topology.boundary_loops, zero_area_faces(V, F))


def _single_texcoords(uv: np.ndarray, topology: MeshTopology) -> np.ndarray:
    """One chart scaled into the unit square at the packing padding (no rotation)."""
    rules = PackingRules()
    used = uv[topology.is_referenced]
    low = used.min(axis=0)
    side = float((used.max(axis=0) - low).max())
    pad = rules.padding / rules.resolution
    texcoords = (uv - low) / side * (1 - 2 * pad) + pad
    texcoords[~topology.is_referenced] = 0.0        # vertices no face uses
    return texcoords



def _result(V: np.ndarray, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
            uv_vertex: np.ndarray, face_chart: np.ndarray, texcoords: np.ndarray,
            flattening: ChartFlattening, opts: ParameterizeOptions, stages: Stages,
            forms: Any, topology: MeshTopology, scale: Packed | None) -> Parameterization:
    """Measures, report and warnings of a layout (one chart or an atlas)."""
    signed_area = signed_areas(uv, uv_faces)
    area3d = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                  axis=1)
    flat = zero_area_faces(V, F)  # collinear corners (issue 40): no flip, no area ratio
    flipped = np.flatnonzero(folded(uv, uv_faces, flat, strict=True))
    ratio = np.divide(signed_area, area3d, out=np.ones_like(signed_area), where=area3d > 0)
    flat3 = np.concatenate([uv, np.zeros((len(uv), 1))], axis=1)
    angle_change = np.abs(corner_angles(flat3, uv_faces) - corner_angles(V, F)).max(axis=1)
    if uv_faces is F:
        length_uv = np.linalg.norm(uv[forms.edges[:, 1]] - uv[forms.edges[:, 0]], axis=1)
        length_change = length_uv / forms.lengths - 1.0
    else:
        length_change = relative_length_change(V, uv, uv_faces, uv_vertex)
    n_charts = int(face_chart.max()) + 1 if len(face_chart) else 0
    seams = seam_edges(topology, face_chart)
    efficiency = packing_efficiency(texcoords, uv_faces)
    rules = PackingRules()
    atlas = {"charts": n_charts, "seam_edges": len(seams),
             "seam_length": float(forms.lengths[seams].sum()),
             "packing_efficiency": efficiency,
             "padding": (scale.padding if scale is not None
                         else rules.padding / rules.resolution),
             "padding_texels": rules.padding,
             "atlas_texels": scale.side_texels if scale is not None else rules.resolution,
             "uv_count": len(uv), "seams": opts.seams,
             "boundary_crossings": _crossings(uv, uv_faces) if scale is None else 0}
    warnings = as_report(flattening_warnings(
        len(flipped), len(F),
        float(np.abs(length_change).mean()) if len(length_change) else 0.0,
        float(angle_change.mean()) if len(F) else 0.0, flattening.refinement,
        packing=efficiency, charts=n_charts, crossings=atlas["boundary_crossings"] or 0))
    refinement = flattening.refinement
    if not warnings:  # the quality targets met: a stall is the flattening's end
        refinement = stalled_at_targets(dict(refinement))
    report = ParameterizeReport(
        flipped_count=len(flipped), area_ratio_summary=summary(ratio - 1.0),
        angle_distortion_summary=summary(angle_change),
        length_change_summary=summary(length_change),
        angle_distortion_histogram=histogram(angle_change),
        length_change_histogram=histogram(length_change),
        planarity_error=flattening.planarity,
        orthonormalized=bool(opts.orthonormalize), refinement=refinement,
        anchored_components=flattening.anchored, backend=flattening.backend,
        analysis=flattening.analysis, timings=stages.timings, atlas=atlas,
        warnings=warnings)
    if len(flat):  # collinear corners (issue 40): counted
        report.input = {"zero_area_faces": len(flat)}
    return Parameterization(uv=uv, flipped_faces=flipped, area_ratio=ratio,
                            angle_distortion=angle_change, report=report,
                            texcoords=texcoords, uv_faces=uv_faces, uv_vertex=uv_vertex,
                            face_chart=face_chart)


def _crossings(uv: np.ndarray, faces: np.ndarray, most: int = 20_000) -> int | None:
    """Crossing boundary-edge pairs of a one-chart layout (None past ``most`` boundary
    edges: the test is quadratic in them). An atlas's charts are each checked while cut
    and packed apart, so an atlas reports 0."""
    half = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2), 1)
    _, count = np.unique(half, axis=0, return_counts=True)
    return None if (count == 1).sum() > most else boundary_crossings(uv, faces)


def _on_file_vertices(flat: Parameterization, cut: ManifoldCut) -> Parameterization:
    """A flattening of a non-manifold mesh's manifold cut, told in the file's vertices: the
    uv indices stay (a cut vertex is one more uv index, as a seam vertex is) and
    ``uv_vertex`` names the file vertex of each (``report["input"]["cut"]``; a welded
    mesh's ``uv_vertex`` names representatives, ``report["input"]["weld"]``)."""
    if flat.uv_vertex is not None:
        flat.uv_vertex = cut.vertex_map[flat.uv_vertex]
    flat.report.input = {**(flat.report.input or {}), **cut.sections()}
    return flat


__all__ = ["Parameterization", "parameterize"]
