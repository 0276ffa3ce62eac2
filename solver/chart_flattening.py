"""One chart flattened by the quasi-isometric method: every dihedral angle set to 0 and
the surface reconstructed (Sec. 5).

With all angles 0 the transition rotations are rotations about the normal, so the anchored
reconstruction lies exactly in the plane z = 0 and keeps the first fundamental form (edge
lengths) as well as a planar immersion can. The optional second solve (Sec. 4) pulls each
frame's in-plane 2x2 block towards the nearest 2D rotation; projecting in 2D (not 3D) keeps
the result planar. The planar refinement (:mod:`solver.refine`, ``dim=2``) then fits the
edge lengths and pushes flipped faces back, begun at local/global steps from a Tutte
embedding. Flipped faces (negative signed area in uv) are reported, never hidden.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from .atlas_rules import ATLAS_RULES
from .linalg import factorize
from .linear.system import half_cotangents
from .mesh.forms import flat_faces
from .mesh.frames import face_edge_lengths, triangle_areas, triangle_layouts
from .mesh.packing import folded
from .mesh.topology import MeshTopology
from .options import ParameterizeOptions
from .reconstruct import ImmersionProblem, Progress
from .refine.outcomes import not_refined
from .refine.refiner import FormTargets, Refiner
from .reports import Stages


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
    """Tutte's embedding (n, 2) of every component: its longest boundary loop on a circle (by
    arc length), every other vertex at the mean of its neighbours (uniform Laplacian), scaled
    to the component's target area.

    Flip-free for a disk (Tutte's theorem); with more holes a good start all the same. The
    components (charts flattened together, :func:`solver.atlas.chart_layouts`) are laid out
    each on its own circle about the origin, by one solve. Returns None unless every component
    with faces has a boundary. Unused vertices stay at 0.
    """
    loops = topology.boundary_loops
    F = topology.faces
    if not loops or not len(F):
        return None
    loop_component = np.asarray(topology.boundary_loop_component)
    sizes = np.array([len(loop) for loop in loops])
    # Each component's longest loop (the first of equals, in the topology's loop order).
    order = np.lexsort((np.arange(len(loops)), -sizes, loop_component))
    first = order[np.r_[True, loop_component[order][1:] != loop_component[order][:-1]]]
    with_faces = np.unique(topology.face_component)
    if not np.array_equal(np.sort(loop_component[first]), with_faces):
        return None
    n = topology.n_vertices
    ring = np.concatenate([loops[i] for i in first])                  # (r,) loop vertices
    length = sizes[first]
    start = np.repeat(np.cumsum(length) - length, length)             # (r,) loop's first
    position = np.arange(len(ring)) - start
    following = ring[start + (position + 1) % np.repeat(length, length)]
    closing = np.linalg.norm(vertices[following] - vertices[ring], axis=1)
    before = np.cumsum(closing) - closing                             # arc length before
    before -= before[start]
    total = np.repeat(np.add.reduceat(closing, np.cumsum(length) - length), length)
    angle = 2 * np.pi * before / total
    uv = np.zeros((n, 2))
    uv[ring] = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    edges = topology.edges
    A = sp.coo_array((np.ones(2 * len(edges)), (np.concatenate([edges[:, 0], edges[:, 1]]),
                                               np.concatenate([edges[:, 1], edges[:, 0]]))),
                     shape=(n, n)).tocsr()
    L = sp.diags_array(np.asarray(A.sum(axis=1)).ravel()) - A
    on_ring = np.zeros(n, dtype=bool)
    on_ring[ring] = True
    inner = np.flatnonzero(topology.is_referenced & ~on_ring)
    if len(inner):
        rhs = -(L[inner][:, ring] @ uv[ring])
        uv[inner] = factorize(L[inner][:, inner], backend,
                              assume_symmetric=True).solve(rhs)
    e1, e2 = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    components = topology.n_components
    area = 0.5 * np.bincount(topology.face_component, e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0],
                             components)
    mirrored = area < 0  # the loop ran clockwise: mirror
    uv[mirrored[topology.vertex_component], 1] *= -1
    area = np.abs(area)
    if (area[with_faces] <= 0).any():
        return None
    target = np.bincount(topology.face_component,
                         triangle_areas(face_edge_lengths(topology, lengths)), components)
    scale = np.sqrt(np.divide(target, area, out=np.zeros(components), where=area > 0))
    return uv * scale[topology.vertex_component][:, None]


def local_global_flattening(topology: MeshTopology, lengths: np.ndarray, uv: np.ndarray,
                            iterations: int = 30, backend: str = "auto") -> np.ndarray:
    """As-rigid-as-possible flattening by local/global steps (Liu et al. 2008) from ``uv``.

    Each face's layout (from ``lengths``) is fitted by a rotation (local step); then every
    vertex is placed by one prefactorized cotangent-Laplacian solve (global step; weights
    clamped to at least 1e-3 of their mean so the matrix stays positive definite, one vertex
    pinned). A robust start for the planar refinement where the linear answer folds.
    Returns (n, 2) float64.
    """
    F = topology.faces
    n = topology.n_vertices
    layouts = triangle_layouts(face_edge_lengths(topology, lengths), check=False)  # (m, 3, 2)
    w = np.abs(half_cotangents(face_edge_lengths(topology, lengths)))     # (m, 3), edge k
    # Each component's weights clamped by its own median and mean (zero-area faces: huge,
    # not dominant, weights), so that components flattened together fit as they would alone.
    component = np.repeat(topology.face_component, 3).reshape(w.shape)
    w = np.minimum(w, 1e4 * _group_median(w, component)[component])
    w = np.maximum(w, 1e-3 * _group_mean(w, component)[component])
    tail, head = F, np.roll(F, -1, axis=1)                                 # half-edge k
    rest = np.roll(layouts, -1, axis=1) - layouts                          # (m, 3, 2)
    rows = np.concatenate([tail.ravel(), head.ravel(), tail.ravel(), head.ravel()])
    cols = np.concatenate([head.ravel(), tail.ravel(), tail.ravel(), head.ravel()])
    vals = np.concatenate([-w.ravel(), -w.ravel(), w.ravel(), w.ravel()])
    L = sp.coo_array((vals, (rows, cols)), shape=(n, n)).tocsr()
    pinned = np.zeros(n, dtype=bool)
    _, first_face = np.unique(topology.face_component, return_index=True)
    pinned[F[first_face, 0]] = True                  # one vertex of each component
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


def _group_median(values: np.ndarray, group: np.ndarray) -> np.ndarray:
    """(groups,) the median of ``values`` in each group (``np.median``'s, per group; 0 for a
    group without values)."""
    values, group = values.ravel(), group.ravel()
    order = np.lexsort((values, group))
    count = np.bincount(group)
    first = np.cumsum(count) - count
    low = first + np.maximum(count - 1, 0) // 2
    high = first + count // 2
    ordered = values[order]
    median = np.zeros(len(count))
    has = count > 0
    median[has] = 0.5 * (ordered[low[has]] + ordered[np.minimum(high[has], len(ordered) - 1)])
    return median


def _group_mean(values: np.ndarray, group: np.ndarray) -> np.ndarray:
    """(groups,) the mean of ``values`` in each group (0 for a group without values)."""
    count = np.bincount(group.ravel())
    return np.bincount(group.ravel(), values.ravel()) / np.maximum(count, 1)


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


DEVELOPABLE = "exact: the surface is developable"
"""Why a chart whose linear flattening already has its edge lengths is not refined."""


def refine_chart(V: np.ndarray, topology: MeshTopology, lengths: np.ndarray,
                 opts: ParameterizeOptions, stages: Stages, linear: ChartFlattening,
                 progress: Progress | None = None,
                 start: tuple[np.ndarray, str] | None = None) -> ChartFlattening:
    """The planar refinement of :func:`flatten_chart`'s linear answer ``linear``, begun at
    ``start`` ((n, 2) uv and its name for the report) when given, else at local/global steps
    from a Tutte embedding computed here."""
    backend = opts.backend or "auto"
    uv = linear.uv
    refiner = Refiner(FormTargets(topology, lengths, np.zeros_like(lengths),
                                  area_weight=opts.area_weight), dim=2, backend=backend)
    if refiner.reproduces(uv):
        refinement = not_refined(DEVELOPABLE)
    else:
        stages("refine")
        # Start from local/global steps begun at a Tutte embedding (robust under large
        # distortion: bumpy-plane 0 flips against 4-146 from the folded linear answer,
        # docs/refinement.md), or from the linear answer where there is no Tutte
        # embedding (a component without boundary).
        if start is None:
            start = _tutte_start(V, topology, lengths, backend) or (uv, "linear answer")
        refiner.expect_refresh(stages.timings.get("factorize", 0.0))
        fit = refiner.run(start[0], time_limit=stages.left(opts.max_seconds),
                          progress=progress)
        uv, refinement = fit.vertices, dict(fit.report, start=start[1])
        uv, refinement = _push_flips_back(topology, lengths, opts, stages, uv, refinement)
        stages.lap("refine")
        stages("refine", 1.0)
    return ChartFlattening(uv, linear.backend, linear.analysis, linear.planarity, refinement,
                           linear.anchored)


def _tutte_start(V: np.ndarray, topology: MeshTopology, lengths: np.ndarray, backend: str,
                 ) -> tuple[np.ndarray, str] | None:
    """Local/global steps from a Tutte embedding, named, or None without one."""
    tutte = tutte_embedding(V, topology, lengths, backend)
    if tutte is None:
        return None
    return (local_global_flattening(topology, lengths, tutte, backend=backend),
            "local/global from Tutte")


def _push_flips_back(topology: MeshTopology, lengths: np.ndarray, opts: ParameterizeOptions,
                     stages: Stages, uv: np.ndarray, refinement: dict[str, Any],
                     ) -> tuple[np.ndarray, dict[str, Any]]:
    """``uv`` (n, 2) and its refinement report, continued with a heavier signed-area weight
    (:attr:`~solver.atlas_rules.AtlasRules.flip_retry_area_factor`) when it has flipped
    faces and time is left; the continued answer is kept only when it has fewer flipped
    faces."""
    flat = flat_faces(topology, lengths)  # zero area: no flip (solver.mesh.packing.folded)
    flipped = int(folded(uv, topology.faces, flat, strict=True).sum())
    left = stages.left(opts.max_seconds)
    if flipped == 0 or (left is not None and left <= 0):
        return uv, refinement
    weight = opts.area_weight * ATLAS_RULES.flip_retry_area_factor
    retry = Refiner(FormTargets(topology, lengths, np.zeros_like(lengths), area_weight=weight),
                    dim=2, backend=opts.backend or "auto").run(uv, time_limit=left)
    after = int(folded(retry.vertices, topology.faces, flat, strict=True).sum())
    if after >= flipped:
        return uv, refinement
    return retry.vertices, dict(refinement, flip_retry={
        "area_weight": weight, "flipped_before": flipped, "flipped_after": after,
        "iterations": retry.report.get("iterations")})


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



__all__ = ["ChartFlattening", "flatten_chart", "local_global_flattening",
           "nearest_planar_rotation", "refine_chart", "relative_length_change",
           "tutte_embedding", "uv_edges"]
