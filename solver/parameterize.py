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

from .errors import TopologyError
from .forms import fundamental_forms
from .frames import face_edge_lengths, triangle_areas, triangle_layouts
from .linalg import factorize
from .manifold import ManifoldCut, manifold_topology
from .metrics import corner_angles, histogram, summary
from .options import ParameterizeOptions
from .outcomes import not_refined
from .reconstruct import ImmersionProblem, Progress
from .refine import FormTargets, Refiner
from .reports import ParameterizeReport, Stages
from .serialization import JsonDataclass
from .system import half_cotangents
from .topology import MeshTopology, build_topology
from .validation import as_points
from .warnings import as_report, flattening_warnings


@dataclass
class Parameterization(JsonDataclass):
    """Result of :func:`parameterize`.

    Attributes:
        uv: (n, 2) float64 planar coordinates (same units as the input).
        flipped_faces: (k,) int64 faces whose uv orientation is reversed.
        area_ratio: (m,) float64 uv area / 3D area.
        angle_distortion: (m,) float64 max |corner angle change| per face (radians).
        report: :class:`solver.reports.ParameterizeReport` (summaries, histograms,
            timings, backend, components).
    """

    uv: np.ndarray
    flipped_faces: np.ndarray
    area_ratio: np.ndarray
    angle_distortion: np.ndarray
    report: ParameterizeReport

    _array_fields: ClassVar[dict[str, Any]] = {
        "uv": np.float64, "flipped_faces": np.int64, "area_ratio": np.float64,
        "angle_distortion": np.float64,
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
                    ) -> np.ndarray | None:
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
        uv[inner] = factorize(L[inner][:, inner], assume_symmetric=True).solve(rhs)
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
    clamped to at least 1e-3 of their mean so the matrix stays positive definite, one vertex
    pinned). A robust start for the planar refinement where the linear answer folds.
    Returns (n, 2) float64.
    """
    F = topology.faces
    n = topology.n_vertices
    layouts = triangle_layouts(face_edge_lengths(topology, lengths), check=False)  # (m, 3, 2)
    w = np.abs(half_cotangents(face_edge_lengths(topology, lengths)))     # (m, 3), edge k
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


def parameterize(vertices: ArrayLike, faces: ArrayLike, *,
                 options: ParameterizeOptions | None = None,
                 progress: Progress | None = None, **overrides: Any) -> Parameterization:
    """Flatten a mesh with boundary by reconstructing it with all dihedral angles 0.

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
        progress: optional ``progress(stage, fraction)`` (validate ... refine).
        **overrides: fields of ``options`` given as keywords.

    Returns:
        :class:`Parameterization`: uv (n, 2), flipped faces, per-face distortion and a
        report (summaries, histograms, ``timings`` per stage, backend).

    Raises:
        TopologyError: a component without boundary (a closed surface cannot be flattened
            without a cut).

    Example:
        >>> import numpy as np
        >>> from solver import parameterize
        >>> V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
        >>> F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> flat = parameterize(V, F)
        >>> flat.uv.shape, len(flat.flipped_faces)
        ((5, 2), 0)
    """
    opts = ParameterizeOptions.given(options, overrides)
    cut = manifold_topology(faces, as_points(vertices, "vertices"))[0]
    if not cut.is_identity:  # a non-manifold mesh: flattened on its cut (solver.manifold)
        return _on_file_vertices(parameterize(cut.to_cut(as_points(vertices, "vertices")),
                                              cut.faces, options=opts, progress=progress), cut)
    backend = opts.backend or "auto"
    stages = Stages(progress)
    stages("validate")
    V = as_points(vertices, "vertices")
    topology = build_topology(faces, n_vertices=len(V))
    closed = [c["component"] for c in topology.component_summary() if c["closed"]]
    if closed:
        raise TopologyError(
            f"component {closed[0]} is a closed surface: it has no boundary, so it cannot be "
            "flattened; cut it open along a seam (duplicate the seam vertices) first",
            field="faces", details={"closed_components": closed})
    forms = fundamental_forms(V, topology.faces)
    stages.lap("validate")
    stages("assemble")
    problem = ImmersionProblem(topology, forms.lengths, np.zeros_like(forms.angles),
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
    uv = flat[:, :2]
    # Used vertices lie in z = 0 exactly (see module docstring); report any deviation.
    planarity = float(np.abs(flat[topology.is_referenced, 2]).max())
    refinement: dict[str, Any] = not_refined("disabled (refine=false)")
    if opts.refine is not False:
        refiner = Refiner(FormTargets(topology, forms.lengths, np.zeros_like(forms.angles),
                                      area_weight=opts.area_weight), dim=2, backend=backend)
        if refiner.reproduces(uv):
            refinement = not_refined("exact: the surface is developable")
        else:
            stages("refine")
            # Start from local/global steps begun at a Tutte embedding (robust under large
            # distortion: bumpy-plane 0 flips against 4-146 from the folded linear answer,
            # docs/refinement.md), or from the linear answer where there is no Tutte
            # embedding (several components).
            tutte = tutte_embedding(V, topology, forms.lengths)
            start, name = uv, "linear answer"
            if tutte is not None:
                start = local_global_flattening(topology, forms.lengths, tutte, backend=backend)
                name = "local/global from Tutte"
            refiner.expect_refresh(stages.timings.get("factorize", 0.0))
            fit = refiner.run(start, time_limit=stages.left(opts.max_seconds),
                              progress=progress)
            uv, refinement = fit.vertices, dict(fit.report, start=name)
            stages.lap("refine")
            stages("refine", 1.0)
    F = topology.faces
    e1, e2 = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    signed_area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    area3d = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                  axis=1)
    flipped = np.flatnonzero(signed_area < 0)
    ratio = signed_area / area3d
    flat3 = np.concatenate([uv, np.zeros((len(uv), 1))], axis=1)
    angle_change = np.abs(corner_angles(flat3, F) - corner_angles(V, F)).max(axis=1)
    length_uv = np.linalg.norm(uv[forms.edges[:, 1]] - uv[forms.edges[:, 0]], axis=1)
    length_change = length_uv / forms.lengths - 1.0
    report = ParameterizeReport(
        flipped_count=len(flipped), area_ratio_summary=summary(ratio - 1.0),
        angle_distortion_summary=summary(angle_change),
        length_change_summary=summary(length_change),
        angle_distortion_histogram=histogram(angle_change),
        length_change_histogram=histogram(length_change), planarity_error=planarity,
        orthonormalized=bool(opts.orthonormalize), refinement=refinement,
        anchored_components=anchored, backend=system.backend, analysis=system.analysis,
        timings=stages.timings, warnings=as_report(flattening_warnings(
            len(flipped), len(F), float(np.abs(length_change).max(initial=0.0)), refinement)))
    return Parameterization(uv=uv, flipped_faces=flipped, area_ratio=ratio,
                            angle_distortion=angle_change, report=report)


__all__ = ["Parameterization", "local_global_flattening", "nearest_planar_rotation",
           "parameterize", "tutte_embedding"]


def _on_file_vertices(flat: Parameterization, cut: ManifoldCut) -> Parameterization:
    """A flattening of a manifold cut given per file vertex: each file vertex's uv is the
    mean of its copies' (spread in ``report["input"]["cut"]``)."""
    uv, spread = cut.to_file(flat.uv)
    flat.uv = uv
    flat.report.input = {"cut": cut.report(spread)}
    return flat
