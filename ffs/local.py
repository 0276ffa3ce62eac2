"""The operations in this process through :mod:`solver`, with the client's signatures.

:class:`Local` has the methods of :class:`ffs.client.Client` (one per operation of
:data:`ffs.operations.OPERATIONS`; same arguments, the HTTP option names, the same
:mod:`ffs.results`) and calls the library the way the service's
workers do (``service/worker/tasks.py``: the same options and defaults), so that
``ffs <command>`` gives the same vertices in-process and with ``--server`` (bit for bit with
the same BLAS thread count; other thread counts change the round-off of refined answers).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

import solver
from ffs.results import (
    Blend,
    Forms,
    Integrability,
    Mesh,
    Parameterization,
    ShapeBlend,
    VjpResult,
)
from solver.core.errors import ConstraintError, SolverInputError
from solver.core.serialization import to_jsonable
from solver.options import (
    BlendOptions,
    DeformOptions,
    InterpolateOptions,
    ParameterizeOptions,
    ReconstructOptions,
)
from solver.reports import mesh_summary

Progress = Callable[[str, float], None]


class NotIntegrableError(SolverInputError):
    """``require_integrable`` and the forms fail the check (the service's 422
    ``not-integrable``), naming the worst vertex."""

    kind = "not-integrable"




CONSTRAINT_KINDS = ("positions", "frames")
"""The members of the API's constraints object."""


def _constraints(document: Mapping[str, Any] | None) -> solver.Constraints:
    """The library's constraints of the API's ``{"positions": [...], "frames": [...]}``.

    Raises:
        ConstraintError: Not an object, or a member the API does not take (a typo such as
            ``position`` was ignored here while the service refused it).
    """
    document = document or {}
    if not isinstance(document, Mapping):
        raise ConstraintError('expected an object {"positions": [...], "frames": [...]}',
                              field="constraints")
    for name in document:
        if name not in CONSTRAINT_KINDS:
            raise ConstraintError(f"unknown member {name!r}; constraints take "
                                  f"{' and '.join(CONSTRAINT_KINDS)}",
                                  field=f"constraints.{name}")
    return solver.Constraints.from_records(document.get("positions") or [],
                                           document.get("frames") or [])


def integrability_report(report: solver.IntegrabilityReport) -> Integrability:
    return Integrability(report.integrable, report.max_defect, report.vertex_defect,
                         to_jsonable(report.to_dict()))


class Local:
    """The operations in-process (see the module docstring)."""

    url = None

    def fundamental_forms(self, vertices: Any, faces: Any, *,
                          progress: Progress | None = None) -> Forms:
        forms = solver.fundamental_forms(vertices, faces)
        return Forms(forms.faces, forms.edges, forms.lengths, forms.angles, forms.vertex_map,
                     None if forms.placement is None else forms.placement.to_dict(),
                     forms.weld_map, forms.dropped_faces)

    def check_integrability(self, faces: Any, edges: Any = None, lengths: Any = None,
                            angles: Any = None, *, tol: float | None = None,
                            n_vertices: int | None = None, vertex_map: Any = None,
                            weld_map: Any = None,
                            progress: Progress | None = None) -> Integrability:
        forms = Forms.given(faces, edges, lengths, angles, vertex_map=vertex_map,
                            weld_map=weld_map)
        report = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                            forms.angles, tol=1e-8 if tol is None else tol,
                                            n_vertices=n_vertices, vertex_map=forms.vertex_map,
                                            weld_map=forms.weld_map)
        return integrability_report(report)

    def _checked_first(self, forms: Forms, solve: ReconstructOptions,
                       options: Mapping[str, Any]) -> solver.IntegrabilityReport | None:
        """With ``require_integrable``: the integrability report (raising
        :class:`NotIntegrableError` for forms that fail it), else None."""
        if not options.get("require_integrable"):
            return None
        tolerance = solve.integrability_tol
        report = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                            forms.angles, tol=tolerance,
                                            vertex_map=forms.vertex_map,
                                            weld_map=forms.weld_map)
        if not report.integrable:
            worst = [int(v) for v in report.worst_vertices]
            raise NotIntegrableError(
                f"the forms are not integrable: max defect {report.max_defect:.3g} "
                f"rad (tolerance {tolerance:g} rad); worst vertices {worst}",
                field="vertices", index=worst[0] if worst else None)
        return report

    def reconstruct(self, faces: Any, edges: Any = None, lengths: Any = None,
                    angles: Any = None, *, constraints: Mapping[str, Any] | None = None,
                    refine: bool | None = None, progress: Progress | None = None,
                    align_to: Any = None, vertex_map: Any = None, weld_map: Any = None,
                    placement: Any = None, **options: Any) -> Mesh:
        forms = Forms.given(faces, edges, lengths, angles, vertex_map=vertex_map,
                            weld_map=weld_map, placement=placement)
        solve = ReconstructOptions.from_api({**options, "refine": refine},
                                            ignore=("require_integrable",))
        report_first = self._checked_first(forms, solve, options)
        result = solver.reconstruct(
            forms.faces, forms.edges, forms.lengths, forms.angles,
            constraints=_constraints(constraints),
            options=solve.replace(check_integrability=report_first is None
                                  or report_first.integrable),
            progress=progress, vertex_map=forms.vertex_map, placement=forms.placement,
            weld_map=forms.weld_map)
        report = result.report.to_dict()
        if report_first is not None:
            report = {"integrability": to_jsonable(report_first.summary()), **report}
        faces = np.asarray(forms.faces, dtype=np.int64)
        if forms.vertex_map is not None:  # the answer is on the file's vertices
            faces = np.asarray(forms.vertex_map, dtype=np.int64)[faces]
        vertices = result.vertices
        if align_to is not None:
            alignment = solver.rigid_alignment(vertices, align_to)
            vertices, report["alignment"] = alignment.vertices, alignment.report()
        return Mesh(vertices, faces, report)

    def reconstruct_vjp(self, faces: Any, edges: Any = None, lengths: Any = None,
                        angles: Any = None, *, cotangent: Any,
                        constraints: Mapping[str, Any] | None = None,
                        refine: bool | None = None, progress: Progress | None = None,
                        vertex_map: Any = None, weld_map: Any = None, placement: Any = None,
                        **options: Any) -> VjpResult:
        forms = Forms.given(faces, edges, lengths, angles, vertex_map=vertex_map,
                            weld_map=weld_map, placement=placement)
        solve = ReconstructOptions.from_api({**options, "refine": refine},
                                            ignore=("require_integrable",))
        self._checked_first(forms, solve, options)
        result, vjp = solver.reconstruct_vjp(
            forms.faces, forms.edges, forms.lengths, forms.angles, options=solve,
            constraints=_constraints(constraints), progress=progress,
            vertex_map=forms.vertex_map, placement=forms.placement, weld_map=forms.weld_map)
        grads = vjp.cotangents(np.asarray(cotangent, dtype=np.float64))
        faces = np.asarray(forms.faces, dtype=np.int64)
        if forms.vertex_map is not None:  # the answer is on the file's vertices
            faces = np.asarray(forms.vertex_map, dtype=np.int64)[faces]
        return VjpResult(result.vertices, faces,
                         grads.lengths, grads.angles, grads.positions, grads.frames,
                         to_jsonable(result.report.to_dict()))

    def deform(self, vertices: Any, faces: Any, handles: Sequence[int] | np.ndarray,
               handle_positions: Any, *, rotation_handles: Sequence[Any] | None = None,
               handle_rotations: Any = None, roi: Any = None, refine: bool | None = None,
               progress: Progress | None = None, **options: Any) -> Mesh:
        result = solver.deform(
            vertices, faces, np.asarray(handles, dtype=np.int64),
            np.asarray(handle_positions, dtype=np.float64).reshape(-1, 3),
            rotation_handles=[np.asarray(g, dtype=np.int64) for g in rotation_handles or []]
            or None,
            handle_rotations=(None if not rotation_handles else
                              np.asarray(handle_rotations, dtype=np.float64).reshape(-1, 3, 3)),
            roi=None if roi is None else np.asarray(roi, dtype=np.int64),
            options=DeformOptions.from_api({**options, "refine": refine}), progress=progress)
        return Mesh(result.vertices, np.asarray(faces, dtype=np.int64),
                    result.report.to_dict())

    def parameterize(self, vertices: Any, faces: Any, *, refine: bool | None = None,
                     progress: Progress | None = None, **options: Any) -> Parameterization:
        result = solver.parameterize(
            vertices, faces, options=ParameterizeOptions.from_api({**options, "refine": refine}),
            progress=progress)
        return Parameterization(result.uv, result.flipped_faces, result.report.to_dict(),
                                result.texcoords, result.uv_faces, result.uv_vertex,
                                result.face_chart)

    def interpolate(self, vertices_a: Any, vertices_b: Any, faces: Any,
                    t: float | Sequence[float], *, refine: bool | None = None,
                    progress: Progress | None = None, **options: Any) -> Blend:
        t_value = float(t) if np.ndim(t) == 0 else [float(x) for x in np.ravel(t)]
        vertices, reports = solver.interpolate(
            vertices_a, vertices_b, faces, t_value, return_reports=True,
            options=InterpolateOptions.from_api({**options, "refine": refine}))
        return Blend(t_value, vertices, np.asarray(faces, dtype=np.int64),
                     to_jsonable(reports[0] if np.ndim(t_value) == 0 else reports))

    def _blend(self, shapes: Any, faces: Any, weights: Any, t: Any, refine: bool | None,
               progress: Progress | None, options: Mapping[str, Any]) -> solver.Blend:
        if (weights is None) == (t is None):
            raise SolverInputError("give exactly one of weights and t", field="weights")
        if weights is None:
            from solver.interpolate import two_shape_weights

            weights = two_shape_weights(t)
        return solver.blend(list(np.asarray(shapes, dtype=np.float64)), weights, faces,
                            options=BlendOptions.from_api({**options, "refine": refine}),
                            progress=progress)

    def blend(self, shapes: Any, faces: Any, weights: Any = None, *,
              t: float | Sequence[float] | None = None, refine: bool | None = None,
              progress: Progress | None = None, **options: Any) -> ShapeBlend:
        result = self._blend(shapes, faces, weights, t, refine, progress, options)
        return ShapeBlend(result.weights, result.vertices, result.faces,
                          to_jsonable(result.reports))

    def blend_gltf(self, shapes: Any, faces: Any, weights: Any = None, *,
                   t: float | Sequence[float] | None = None,
                   times: Sequence[float] | None = None, kind: str = "glb",
                   refine: bool | None = None, progress: Progress | None = None,
                   **options: Any) -> bytes:
        from solver.mesh.gltf import encode_gltf_animation

        result = self._blend(shapes, faces, weights, t, refine, progress, options)
        warnings = to_jsonable(result.warnings)
        return encode_gltf_animation(result.vertices, result.faces,
                                     base=np.asarray(shapes, dtype=np.float64)[0],
                                     times=times, kind=kind,  # type: ignore[arg-type]
                                     extras={"warnings": warnings} if warnings else None)

    def mean(self, shapes: Any, faces: Any, *, refine: bool | None = None,
             progress: Progress | None = None, **options: Any) -> Mesh:
        count = len(shapes)  # none: the library names the count (``shapes``)
        result = self.blend(shapes, faces, np.full((1, count), 1.0 / max(count, 1)),
                            refine=refine, progress=progress, **{"align": True, **options})
        return Mesh(result.vertices[0], result.faces, result.reports[0])

    def transfer(self, source: Any, source_deformed: Any, target: Any, faces: Any, *,
                 refine: bool | None = None, progress: Progress | None = None,
                 **options: Any) -> Mesh:
        vertices, report = solver.transfer(
            source, source_deformed, target, faces, return_report=True, progress=progress,
            options=BlendOptions.from_api({**options, "refine": refine}))
        return Mesh(vertices, np.asarray(faces, dtype=np.int64), to_jsonable(report))

    def mesh(self, vertices: Any, faces: Any, *, progress: Progress | None = None) -> Mesh:
        """The mesh checked like the service checks it (``POST /v1/mesh``), its report."""
        return Mesh(*mesh_summary(vertices, faces))
