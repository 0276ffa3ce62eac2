"""Quasi-isometric parameterization: set every dihedral angle to 0 and reconstruct (Sec. 5).

With all angles 0 the transition rotations are rotations about the normal, so the anchored
reconstruction lies exactly in the plane z = 0 and keeps the first fundamental form (edge
lengths) as well as a planar immersion can. The optional second solve (Sec. 4) pulls each
frame's in-plane 2x2 block towards the nearest 2D rotation; projecting in 2D (not 3D) keeps
the result planar. Flipped faces (negative signed area in uv) are reported, never hidden.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from .charts import (
    ChartMesh,
    bisect,
    chart_mesh,
    connected_face_sets,
    dual_graph,
    is_disk_like,
    seam_edges,
)
from .errors import TopologyError
from .forms import fundamental_forms, zero_area_faces
from .frames import face_edge_lengths, triangle_areas, triangle_layouts
from .linalg import factorize
from .manifold import ManifoldCut, manifold_topology
from .metrics import corner_angles, histogram, summary
from .options import ParameterizeOptions
from .outcomes import not_refined, with_outcome
from .packing import (
    Packed,
    PackingRules,
    boundary_crossings,
    pack_charts,
    packing_efficiency,
    signed_areas,
)
from .reconstruct import ImmersionProblem, Progress
from .refine import FormTargets, Refiner
from .reports import ParameterizeReport, Stages
from .serialization import JsonDataclass
from .system import half_cotangents
from .topology import MeshTopology, build_topology
from .validation import as_points
from .warnings import (
    DEFAULT_RULES,
    as_report,
    flattening_warnings,
)


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


def nearest_planar_rotation(frames: np.ndarray) -> np.ndarray:
    """(m, 3, 3) rotations about z closest to the in-plane 2x2 block of each frame."""
    B = frames[:, :2, :2]
    # Closest SO(2) element to B: the rotation by the angle of (B00 + B11, B10 - B01).
    angle = np.arctan2(B[:, 1, 0] - B[:, 0, 1], B[:, 0, 0] + B[:, 1, 1])
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros_like(frames)
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def tutte_embedding(vertices: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
                    backend: str = "auto") -> np.ndarray | None:
    """Tutte's embedding (n, 2): the longest boundary loop on a circle (by arc length), every
    other vertex at the mean of its neighbours (uniform Laplacian), scaled to the target area.

    Flip-free for a disk (Tutte's theorem); with more holes a good start all the same. Returns
    None unless the mesh is one component with a boundary. Unused vertices stay at 0.
    """
    if topology.n_components != 1 or not topology.boundary_loops:
        return None
    loop = max(topology.boundary_loops, key=len)
    n = topology.n_vertices
    closing = np.linalg.norm(np.roll(vertices[loop], -1, axis=0) - vertices[loop], axis=1)
    angle = 2 * np.pi * np.concatenate([[0.0], np.cumsum(closing)[:-1]]) / closing.sum()
    uv = np.zeros((n, 2))
    uv[loop] = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    edges = topology.edges
    A = sp.coo_array((np.ones(2 * len(edges)), (np.concatenate([edges[:, 0], edges[:, 1]]),
                                               np.concatenate([edges[:, 1], edges[:, 0]]))),
                     shape=(n, n)).tocsr()
    L = sp.diags_array(np.asarray(A.sum(axis=1)).ravel()) - A
    inner = np.flatnonzero(topology.is_referenced & ~np.isin(np.arange(n), loop))
    if len(inner):
        rhs = -(L[inner][:, loop] @ uv[loop])
        uv[inner] = factorize(L[inner][:, inner], backend,
                              assume_symmetric=True).solve(rhs)
    F = topology.faces
    e1, e2 = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    if area < 0:  # the loop ran clockwise: mirror
        uv[:, 1] *= -1
        area = -area
    target = triangle_areas(face_edge_lengths(topology, lengths)).sum()
    return uv * np.sqrt(target / area) if area > 0 else None


def local_global_flattening(topology: MeshTopology, lengths: np.ndarray, uv: np.ndarray,
                            iterations: int = 30, backend: str = "auto") -> np.ndarray:
    """As-rigid-as-possible flattening by local/global steps (Liu et al. 2008) from ``uv``.

    Each face's layout (from ``lengths``) is fitted by a rotation (local step); then every
    vertex is placed by one prefactorized cotangent-Laplacian solve (global step; weights
    clamped to at least 1e-3 of their mean so the matrix stays positive definite and to at
    most 1e4 times their median, which only the cotangents of faces of (nearly) zero area
    reach; one vertex pinned). A robust start for the planar refinement where the linear
    answer folds.
    Returns (n, 2) float64.
    """
    F = topology.faces
    n = topology.n_vertices
    layouts = triangle_layouts(face_edge_lengths(topology, lengths), check=False)  # (m, 3, 2)
    w = np.abs(half_cotangents(face_edge_lengths(topology, lengths)))     # (m, 3), edge k
    w = np.minimum(w, 1e4 * np.median(w))  # zero-area faces: huge, not dominant, weights
    w = np.maximum(w, 1e-3 * w.mean())
    tail, head = F, np.roll(F, -1, axis=1)                                 # half-edge k
    rest = np.roll(layouts, -1, axis=1) - layouts                          # (m, 3, 2)
    rows = np.concatenate([tail.ravel(), head.ravel(), tail.ravel(), head.ravel()])
    cols = np.concatenate([head.ravel(), tail.ravel(), tail.ravel(), head.ravel()])
    vals = np.concatenate([-w.ravel(), -w.ravel(), w.ravel(), w.ravel()])
    L = sp.coo_array((vals, (rows, cols)), shape=(n, n)).tocsr()
    pinned = np.zeros(n, dtype=bool)
    pinned[F[0, 0]] = True
    pinned |= ~topology.is_referenced
    free = np.flatnonzero(~pinned)
    factor = factorize(L[free][:, free], backend, assume_symmetric=True)
    coupling = L[free][:, np.flatnonzero(pinned)]
    uv = np.array(uv, dtype=np.float64)
    for _ in range(iterations):
        current = uv[head] - uv[tail]                                      # (m, 3, 2)
        J = np.einsum("tk,tki,tkj->tij", w, current, rest)                 # (m, 2, 2)
        angle = np.arctan2(J[:, 1, 0] - J[:, 0, 1], J[:, 0, 0] + J[:, 1, 1])
        c, s = np.cos(angle), np.sin(angle)
        target = np.stack([c[:, None] * rest[..., 0] - s[:, None] * rest[..., 1],
                           s[:, None] * rest[..., 0] + c[:, None] * rest[..., 1]], -1)
        flow = w[..., None] * target                                      # (m, 3, 2)
        b = np.stack([np.bincount(head.ravel(), flow[..., d].ravel(), n)
                      - np.bincount(tail.ravel(), flow[..., d].ravel(), n)
                      for d in range(2)], axis=1)
        uv[free] = factor.solve(b[free] - coupling @ uv[pinned])
    return uv


@dataclass
class ChartFlattening:
    """One chart flattened by the quasi-isometric method (:func:`flatten_chart`).

    Attributes:
        uv: (n, 2) float64 layout in the chart's units.
        backend, analysis: the factorization's.
        planarity: max |z| of the linear answer.
        refinement: whether and how it refined.
        anchored: ``{"component", "vertex", "face"}`` of each component.
    """

    uv: np.ndarray
    backend: str
    analysis: str
    planarity: float
    refinement: dict[str, Any]
    anchored: list[dict[str, int]]


def flatten_chart(V: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
                  opts: ParameterizeOptions, stages: Stages, *, refine: bool,
                  progress: Progress | None = None) -> ChartFlattening:
    """Today's flattening of one mesh with boundary: the linear solve with all angles 0,
    the orthonormalized second solve, then (``refine``) the planar refinement from
    local/global steps begun at a Tutte embedding (flips pushed back).

    Args:
        V: (n, 3) float64 vertices; topology: its faces; lengths: (E,) its edge lengths.
        opts: the options; stages: timings and progress; refine: whether to refine.
        progress: the refinement's progress callback.
    """
    backend = opts.backend or "auto"
    stages("assemble")
    problem = ImmersionProblem(topology, lengths, np.zeros_like(lengths),
                               frame_weight=opts.frame_weight, weighting=opts.weighting)
    anchor, anchored = problem.anchors(np.ones(topology.n_components, dtype=bool))
    stages.lap("assemble")
    stages("factorize")
    system = problem.system(anchor, backend)
    stages.lap("factorize")
    stages("solve")
    u = system.solve(anchor.hard_values, np.zeros((0, 3)))
    stages.lap("solve")
    if opts.orthonormalize:
        _, frames = problem.unknowns_to_geometry(u)
        targets = np.swapaxes(nearest_planar_rotation(frames), 1, 2).reshape(-1, 3)
        stages("factorize", 0.5)
        # Dropping the first factorization first hands its analysis (same pattern) to this
        # one: only the numerical factorization is redone (solver.linalg's cache).
        del system
        system = problem.system(anchor, backend, problem.all_frame_columns(),
                                opts.orthonormal_weight)
        stages.lap("factorize")
        stages("solve", 0.5)
        u = system.solve(anchor.hard_values, targets)
        stages.lap("solve")
    flat, _ = problem.unknowns_to_geometry(u)
    stages("solve", 1.0)
    # Used vertices lie in z = 0 exactly (see module docstring); report any deviation.
    planarity = float(np.abs(flat[topology.is_referenced, 2]).max())
    linear = ChartFlattening(flat[:, :2], system.backend, system.analysis, planarity,
                             not_refined("disabled (refine=false)"), anchored)
    return refine_chart(V, topology, lengths, opts, stages, linear, progress) if refine \
        else linear


def refine_chart(V: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
                 opts: ParameterizeOptions, stages: Stages, linear: ChartFlattening,
                 progress: Progress | None = None) -> ChartFlattening:
    """The planar refinement of :func:`flatten_chart`'s linear answer ``linear``."""
    backend = opts.backend or "auto"
    uv = linear.uv
    refiner = Refiner(FormTargets(topology, lengths, np.zeros_like(lengths),
                                  area_weight=opts.area_weight), dim=2, backend=backend)
    if refiner.reproduces(uv):
        refinement = not_refined("exact: the surface is developable")
    else:
        stages("refine")
        # Start from local/global steps begun at a Tutte embedding (robust under large
        # distortion: bumpy-plane 0 flips against 4-146 from the folded linear answer,
        # docs/refinement.md), or from the linear answer where there is no Tutte
        # embedding (several components).
        tutte = tutte_embedding(V, topology, lengths, backend)
        start, name = uv, "linear answer"
        if tutte is not None:
            start = local_global_flattening(topology, lengths, tutte, backend=backend)
            name = "local/global from Tutte"
        refiner.expect_refresh(stages.timings.get("factorize", 0.0))
        fit = refiner.run(start, time_limit=stages.left(opts.max_seconds),
                          progress=progress)
        uv, refinement = fit.vertices, dict(fit.report, start=name)
        stages.lap("refine")
        stages("refine", 1.0)
    return ChartFlattening(uv, linear.backend, linear.analysis, linear.planarity, refinement,
                           linear.anchored)


def uv_edges(uv_faces: np.ndarray) -> np.ndarray:
    """(E', 2) int64 the unique edges [i, j], i < j, of ``uv_faces`` over uv indices
    (lexicographic): a seam edge appears once per side."""
    pairs = np.stack([uv_faces, np.roll(uv_faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    return np.unique(np.sort(pairs, axis=1), axis=0)


def relative_length_change(V: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
                           uv_vertex: np.ndarray) -> np.ndarray:
    """(E',) float64 |uv edge| / |3D edge| - 1 over :func:`uv_edges` (3D ends through
    ``uv_vertex``)."""
    edges = uv_edges(uv_faces)
    flat = np.linalg.norm(uv[edges[:, 1]] - uv[edges[:, 0]], axis=1)
    rest = np.linalg.norm(V[uv_vertex[edges[:, 1]]] - V[uv_vertex[edges[:, 0]]], axis=1)
    return flat / rest - 1.0


@dataclass
class ChartLayout:
    """An accepted chart: its mesh (:class:`solver.charts.ChartMesh`) and flattening."""

    mesh: ChartMesh
    flattening: ChartFlattening


def chart_layouts(V: np.ndarray, topology: MeshTopology, angles: np.ndarray,
                  opts: ParameterizeOptions, stages: Stages,
                  progress: Progress | None = None) -> list[ChartLayout]:
    """Cut the mesh into charts and flatten each (the seams of :mod:`solver.charts`).

    Starting from the edge-connected components, a chart is bisected while it is closed
    or has a handle, while its linear flattening's mean relative length change is above
    twice ``opts.max_chart_distortion``, or while its refined flattening is above it, has
    a flipped face or overlaps itself. A loop over charts; each chart's work is vectorized.
    ``progress("charts", fraction of faces placed)``.
    """
    faces = topology.faces
    m = len(faces)
    graph = dual_graph(V, topology, angles, opts.crease_weight)
    queue = connected_face_sets(graph, np.arange(m), m)
    quiet = Stages(None)
    done: list[ChartLayout] = []
    placed = 0
    while queue:
        ids = queue.pop()
        chart = chart_mesh(faces, ids)
        flattening = _flatten_or_none(V[chart.vertex_ids], chart.faces,
                                      _chart_options(opts, len(ids)), quiet,
                                      out_of_time=_out_of_time(stages, opts))
        if flattening is None:
            queue.extend(bisect(graph, ids, m))
            continue
        done.append(ChartLayout(chart, flattening))
        placed += len(ids)
        stages("charts", placed / m)
    for stage, seconds in quiet.timings.items():
        stages.timings[stage] = stages.timings.get(stage, 0.0) + seconds
    return done


def _out_of_time(stages: Stages, opts: ParameterizeOptions) -> bool:
    left = stages.left(opts.max_seconds)
    return left is not None and left <= 0


def _flatten_or_none(V: np.ndarray, faces: np.ndarray, opts: ParameterizeOptions,
                     stages: Stages, *, out_of_time: bool) -> ChartFlattening | None:
    """The chart's flattening, or None when it is to be split (see :func:`chart_layouts`);
    a single face, or any chart once the time is out, is always kept."""
    topology = build_topology(faces, n_vertices=len(V))
    if len(faces) == 1:
        corners = triangle_layouts(face_edge_lengths(topology, _lengths(V, topology)),
                                   check=False)[0]                    # (3, 2) per corner
        layout = np.zeros((len(V), 2))
        layout[faces[0]] = corners                                        # per chart vertex
        return ChartFlattening(layout, "none", "", 0.0, {"refined": False,
                                                          "reason": "one face"}, [])
    if not is_disk_like(topology):
        return None if not out_of_time else _last_resort(V, topology, opts, stages)
    lengths = _lengths(V, topology)
    limit = opts.max_chart_distortion
    quick = flatten_chart(V, topology, lengths, opts, stages, refine=False)
    if not out_of_time and _mean_change(V, quick.uv, faces) > 2 * limit:
        return None
    full = quick if opts.refine is False else refine_chart(V, topology, lengths, opts, stages,
                                                            quick)
    if out_of_time:
        return full
    if _folded(V, full.uv, faces).any() or _mean_change(V, full.uv, faces) > limit \
            or _overlaps_itself(V, full.uv, faces):
        return None
    return full


def _last_resort(V: np.ndarray, topology: MeshTopology, opts: ParameterizeOptions,
                 stages: Stages) -> ChartFlattening | None:
    """Out of time with a closed chart: it must still be cut (None) unless it is open."""
    if any(c["closed"] for c in topology.component_summary()):
        return None
    return flatten_chart(V, topology, _lengths(V, topology), opts, stages, refine=False)


def _lengths(V: np.ndarray, topology: MeshTopology) -> np.ndarray:
    return np.linalg.norm(V[topology.edges[:, 1]] - V[topology.edges[:, 0]], axis=1)


def _mean_change(V: np.ndarray, uv: np.ndarray, faces: np.ndarray) -> float:
    identity = np.arange(len(V))
    return float(np.abs(relative_length_change(V, uv, faces, identity)).mean())


def _folded(V: np.ndarray, uv: np.ndarray, faces: np.ndarray, strict: bool = False,
            ) -> np.ndarray:
    """(m,) bool, the faces flipped in ``uv`` (signed area <= 0; < 0 with ``strict``),
    except faces of zero area in ``V`` (collinear corners, issue 40): flat in 3D, their uv
    area is 0 up to rounding, of either sign, and says nothing about a fold."""
    area = signed_areas(uv, faces)
    folded = area < 0 if strict else area <= 0
    if folded.any():
        folded[zero_area_faces(V, faces)] = False
    return folded


def _overlaps_itself(V: np.ndarray, uv: np.ndarray, faces: np.ndarray) -> bool:
    """Whether a chart's layout overlaps itself: a flipped face (:func:`_folded`), or
    boundary edges that cross (:func:`solver.packing.boundary_crossings`)."""
    return bool(_folded(V, uv, faces).any()) or boundary_crossings(uv, faces) > 0


SMALL_CHART_FACES = 20_000
"""Charts with fewer faces are solved with SuperLU when the backend is ``auto``: PARDISO's
fixed cost per call (measured 0.95 s against 0.10 s per 456-face flattening) dominates
there."""


def _chart_options(opts: ParameterizeOptions, faces: int) -> ParameterizeOptions:
    if (opts.backend or "auto") == "auto" and faces < SMALL_CHART_FACES:
        return opts.replace(backend="superlu")
    return opts


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
    :func:`solver.packing.pack_charts` packs them. ``seams="none"``: one chart per
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
    cut = manifold_topology(faces, as_points(vertices, "vertices"))[0]
    if not cut.is_identity:  # a non-manifold mesh: flattened on its cut (solver.manifold)
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
    forms = fundamental_forms(V, topology.faces)
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
    charts = chart_layouts(V, topology, forms.angles, opts, stages, progress)
    stages("pack")
    layout, uv_faces, uv_vertex, face_chart = _assemble(charts, len(F))
    packed = pack_charts(layout, uv_faces, face_chart)
    stages.lap("pack")
    last = max(charts, key=lambda chart: len(chart.mesh.face_ids)).flattening
    summary_refinement = with_outcome({
        "refined": any(c.flattening.refinement.get("refined") for c in charts),
        "converged": all(c.flattening.refinement.get("converged", True) for c in charts),
        "reason": f"per chart ({len(charts)} charts)"})
    combined = ChartFlattening(packed.texcoords * packed.scale, last.backend, last.analysis,
                               max(c.flattening.planarity for c in charts),
                               summary_refinement, [])
    return _result(V, F, combined.uv, uv_faces, uv_vertex, face_chart, packed.texcoords,
                   combined, opts, stages, forms, topology, scale=packed)


def _keeps_single_chart(V: np.ndarray, uv: np.ndarray, topology: MeshTopology,
                        opts: ParameterizeOptions) -> bool:
    """Whether today's single chart stands: a disk-like mesh whose flattening has at most
    :attr:`WarningRules.max_flipped_fraction` flipped faces (a local fold, which also
    overlaps locally; without flips, no overlap at all) and a mean relative length change
    of at most twice ``max_chart_distortion`` (the bumpy plane's 0.055 stays one chart)."""
    F = topology.faces
    if not is_disk_like(topology):
        return False
    flipped = int(_folded(V, uv, F, strict=True).sum())
    if flipped > DEFAULT_RULES.max_flipped_fraction * len(F):
        return False
    if _mean_change(V, uv, F) > 2 * opts.max_chart_distortion:
        return False
    return flipped > 0 or boundary_crossings(uv, F) == 0


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


def _assemble(charts: list[ChartLayout], m: int,
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


def _result(V: np.ndarray, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
            uv_vertex: np.ndarray, face_chart: np.ndarray, texcoords: np.ndarray,
            flattening: ChartFlattening, opts: ParameterizeOptions, stages: Stages,
            forms: Any, topology: MeshTopology, scale: Packed | None) -> Parameterization:
    """Measures, report and warnings of a layout (one chart or an atlas)."""
    signed_area = signed_areas(uv, uv_faces)
    area3d = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                  axis=1)
    folded = signed_area < 0
    folded[zero_area_faces(V, F)] = False  # flat in 3D: no fold (see _folded)
    flipped = np.flatnonzero(folded)
    # A face of zero area (issue 40) has no area ratio: counted as 1 (unchanged).
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
    report = ParameterizeReport(
        flipped_count=len(flipped), area_ratio_summary=summary(ratio - 1.0),
        angle_distortion_summary=summary(angle_change),
        length_change_summary=summary(length_change),
        angle_distortion_histogram=histogram(angle_change),
        length_change_histogram=histogram(length_change),
        planarity_error=flattening.planarity,
        orthonormalized=bool(opts.orthonormalize), refinement=flattening.refinement,
        anchored_components=flattening.anchored, backend=flattening.backend,
        analysis=flattening.analysis, timings=stages.timings, atlas=atlas,
        warnings=warnings)
    if forms.zero_area_faces is not None:  # collinear corners (issue 40): counted
        report.input = {"zero_area_faces": len(forms.zero_area_faces)}
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
    ``uv_vertex`` names the file vertex of each (``report["input"]["cut"]``)."""
    if flat.uv_vertex is not None:
        flat.uv_vertex = cut.vertex_map[flat.uv_vertex]
    flat.report.input = {**(flat.report.input or {}), "cut": cut.report()}
    return flat


__all__ = ["ChartFlattening", "ChartLayout", "Parameterization",
           "chart_layouts", "flatten_chart", "local_global_flattening",
           "nearest_planar_rotation", "parameterize", "relative_length_change",
           "tutte_embedding", "uv_edges"]
