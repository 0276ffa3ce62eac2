"""The operations' task functions, run in the worker processes.

Each takes a :class:`service.api.task.TaskRequest` whose source is decoded (numpy arrays or
an uploaded file) and a ``progress(stage, fraction)`` callback, calls :mod:`solver`, and
returns a :class:`service.api.task.TaskResult` with the response body in the requested
format. Client-caused failures raise :class:`service.api.problems.ProblemError` or the
solver's :class:`solver.core.errors.SolverInputError` (a mesh file's names the upload), turned
into the failure the worker sends by :func:`service.api.problems.failure_of`. The registry
(:data:`service.operations.OPERATIONS`) names the task of each operation.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

import solver
from service.api.decoding import check_limits, check_work
from service.api.problems import ProblemError, element_error
from service.api.task import (
    FormsArrays,
    MeshArrays,
    MeshFile,
    MeshPair,
    MeshStack,
    MeshTriple,
    TaskRequest,
    TaskResult,
)
from service.worker import output
from solver.mesh import gltf

Progress = Callable[[str, float], None]
TaskFn = Callable[[TaskRequest, Progress], TaskResult]


# ------------------------------------------------------------------------------ inputs


def _load_file(upload: MeshFile, request: TaskRequest) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces, _ = _read_file(upload, request)
    return vertices, faces


def _read_file(upload: MeshFile, request: TaskRequest
               ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """An upload's vertices, triangles and the ``input`` report of its reading (polygons
    triangulated, :func:`solver.mesh.io.read_mesh`)."""
    from solver.mesh.io import MeshFileError, read_mesh

    try:
        loaded = read_mesh(upload.data, upload.filename)
    except MeshFileError as exc:  # its problem names the upload's field and file name
        exc.located(field=upload.field, file_name=upload.filename)
        raise
    check_limits(len(loaded.vertices), len(loaded.faces), request.limits.answering(request.params),
                 upload.field)
    return loaded.vertices, loaded.faces, loaded.report()


def _mesh(request: TaskRequest) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces, _ = _mesh_and_input(request)
    return vertices, faces


def _mesh_and_input(request: TaskRequest) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The request's mesh and the ``input`` report of reading it ({} for arrays)."""
    source = request.source
    if isinstance(source, MeshFile):
        return _read_file(source, request)
    assert isinstance(source, MeshArrays)
    return source.vertices, source.faces, {}


def _with_input(report: dict[str, Any], read: dict[str, Any]) -> dict[str, Any]:
    """A report with the file's reading (polygons) added to its ``input`` section."""
    if read:
        report["input"] = {**read, **(report.get("input") or {})}
    return report


def _forms(request: TaskRequest) -> tuple[FormsArrays, int | None]:
    """Forms from the request (computed from the mesh for a file upload) and n_vertices;
    a non-manifold mesh's forms carry the cut's ``vertex_map`` (solver.mesh.manifold)."""
    if isinstance(request.source, FormsArrays):
        params = request.params
        vertex_map, weld_map = params.get("vertex_map"), params.get("weld_map")
        return dataclasses.replace(
            request.source, placement=params.get("placement"),
            vertex_map=None if vertex_map is None else np.asarray(vertex_map, np.int64),
            weld_map=None if weld_map is None else np.asarray(weld_map, np.int64)), None
    vertices, faces = _mesh(request)
    forms = solver.fundamental_forms(vertices, faces)
    return FormsArrays(forms.faces, forms.edges, forms.lengths, forms.angles,
                       forms.vertex_map, forms.placement, forms.weld_map), len(vertices)


def _file_faces(forms: FormsArrays) -> np.ndarray:
    """The answer's faces: the forms' faces on the file's vertices."""
    faces = np.asarray(forms.faces)
    return faces if forms.vertex_map is None else np.asarray(forms.vertex_map)[faces]


def _answer_warnings(document: dict[str, Any]) -> list[dict[str, Any]]:
    """The warnings of an answer's report (``report["warnings"]``; [] without a report)."""
    report = document.get("report")
    try:
        return list(report["warnings"] or []) if report is not None else []
    except (KeyError, TypeError):
        return []


def _finish(request: TaskRequest, progress: Progress, document: dict[str, Any],
            mesh: tuple[np.ndarray, np.ndarray] | None = None,
            colors: dict[str, np.ndarray] | None = None,
            texcoords: np.ndarray | None = None) -> TaskResult:
    """The encode stage: the response body in the requested format (+ kept data for jobs)."""
    progress("encode", 0.0)
    out = request.output
    colors = colors or {}
    values = colors.get(out.color) if out.color else None
    if out.format == "json":
        if values is not None:
            document["colors"] = output.colors_for(values)
        body = output.json_bytes(document)
    else:
        if mesh is None:
            raise ProblemError("not-acceptable", "this result is not a single mesh")
        body = output.mesh_bytes(out.format, mesh[0], mesh[1], values, texcoords,
                                 _answer_warnings(document))
    result = TaskResult(output.MEDIA_TYPES[out.format], body)
    if out.keep:
        result.mesh, result.colors = mesh, colors
        result.texcoords = texcoords
    progress("encode", 1.0)
    return result


# ------------------------------------------------------------------------------- tasks


def forms_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """Edge lengths and dihedral angles of a mesh."""
    progress("validate", 0.0)
    vertices, faces = _mesh(request)
    progress("solve", 0.0)
    forms = solver.fundamental_forms(vertices, faces)
    document = {"faces": forms.faces, "edges": forms.edges, "lengths": forms.lengths,
                "angles": forms.angles, "placement": forms.placement.to_dict()}
    for name in ("vertex_map", "weld_map", "dropped_faces"):
        if getattr(forms, name) is not None:
            document[name] = getattr(forms, name)
    if forms.zero_area_faces is not None:
        document["zero_area_faces"] = forms.zero_area_faces
    return _finish(request, progress, document)


def integrability_document(report: solver.IntegrabilityReport) -> dict[str, Any]:
    """The API shape of an :class:`solver.IntegrabilityReport`."""
    return {
        "integrable": report.integrable, "local_integrable": report.local_integrable,
        "global_integrable": report.global_integrable, "max_defect": report.max_defect,
        "tolerance": report.tolerance, "vertex_defect": report.vertex_defect,
        "gauss_defect": report.gauss_defect, "codazzi_defect": report.codazzi_defect,
        "failing_vertices": report.failing_vertices, "worst_vertices": report.worst_vertices,
        "triangle_violations": report.triangle_violations,
        "topology": {"n_components": report.n_components,
                     "euler_characteristic": report.euler_characteristic,
                     "genus": report.genus, "boundary_loops": report.boundary_loops,
                     "isolated_vertices": report.isolated_vertices,
                     "components": report.components},
        "global_holonomy": {"rotation": [g.to_dict() for g in report.rotation_holonomy],
                            "translation": [g.to_dict() for g in report.translation_holonomy]},
        "wrapped_angles": report.wrapped_angles,
    }


def integrability_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """The integrability report of a set of forms (or of a mesh file's forms)."""
    progress("validate", 0.0)
    forms, n_vertices = _forms(request)
    progress("solve", 0.0)
    report = solver.check_integrability(forms.faces, forms.edges, forms.lengths, forms.angles,
                                        tol=request.params["tolerance"], n_vertices=n_vertices,
                                        vertex_map=forms.vertex_map, weld_map=forms.weld_map)
    return _finish(request, progress, integrability_document(report))


def _not_integrable(report: solver.IntegrabilityReport) -> ProblemError:
    """422 ``not-integrable`` naming the worst vertices, failing loops and bad triangles."""
    errors: list[dict[str, Any]] = [
        {"field": "vertices", "index": int(v), "reason":
         f"holonomy defect {report.vertex_defect[v]:.3g} rad around vertex {int(v)} exceeds "
         f"the tolerance {report.tolerance:g}", "defect": float(report.vertex_defect[v])}
        for v in report.worst_vertices if report.vertex_defect[v] > report.tolerance]
    for loop in report.rotation_holonomy + report.translation_holonomy:
        if not loop.passes:
            what = ("rotation" if loop.kind == "rotation" else "translation")
            errors.append({"field": "edges", "index": loop.edge_index,
                           "reason": f"global {what} holonomy {loop.magnitude:.3g} along the "
                                     f"generator loop closed by edge {loop.edge}",
                           "magnitude": loop.magnitude})
    errors.extend({"field": "faces", "index": int(t),
                   "reason": "edge lengths violate the triangle inequality"}
                  for t in report.triangle_violations[:20])
    worst = [int(v) for v in report.worst_vertices]
    return ProblemError(
        "not-integrable",
        f"the forms are not integrable: max defect {report.max_defect:.3g} rad (tolerance "
        f"{report.tolerance:g} rad); worst vertices {worst}", errors=errors,
        worst_vertices=worst, integrability=report.summary())


def _constraints(data: dict[str, Any] | None) -> solver.Constraints | None:
    """The solver's constraints of the request's ``constraints`` document."""
    data = data or {}
    return solver.Constraints.from_records(data.get("positions") or [],
                                           data.get("frames") or [])


def reconstruct_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """Vertex positions from forms; validates integrability first (see the API docs)."""
    params = request.params
    options = request.solve_options(solver.ReconstructOptions)
    require_integrable = params["options"]["require_integrable"]
    progress("validate", 0.0)
    forms, n_vertices = _forms(request)
    full_report = None
    if require_integrable or request.output.wants("defect"):
        full_report = solver.check_integrability(
            forms.faces, forms.edges, forms.lengths, forms.angles,
            tol=options.integrability_tol, n_vertices=n_vertices, vertex_map=forms.vertex_map,
            weld_map=forms.weld_map)
        if require_integrable and not full_report.integrable:
            raise _not_integrable(full_report)
    result = solver.reconstruct(
        forms.faces, forms.edges, forms.lengths, forms.angles,
        constraints=_constraints(params.get("constraints")), n_vertices=n_vertices,
        # Integrable forms are checked again inside: their verdict (with the linear energy)
        # spares them a refinement (solver.reconstruct.linear_answer_is_exact).
        options=options.replace(check_integrability=full_report is None
                                or full_report.integrable), progress=progress,
        vertex_map=forms.vertex_map, placement=forms.placement, weld_map=forms.weld_map)
    report = result.report.to_dict()
    if full_report is not None:
        report = {"integrability": full_report.summary(), **report}
    vertices = result.vertices
    if params.get("align_to") is not None:
        alignment = solver.rigid_alignment(vertices, params["align_to"])
        vertices, report["alignment"] = alignment.vertices, alignment.report()
    faces = _file_faces(forms)
    colors = {"defect": full_report.vertex_defect} if full_report is not None else {}
    document = {"vertices": vertices, "faces": faces, "report": report}
    return _finish(request, progress, document, (vertices, faces), colors)


def reconstruct_vjp_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """A reconstruction and the cotangents of its inputs for the request's ``cotangent``
    (:func:`solver.reconstruct_vjp`)."""
    params = request.params
    options = request.solve_options(solver.ReconstructOptions)
    progress("validate", 0.0)
    forms, n_vertices = _forms(request)
    if params["options"]["require_integrable"]:
        report = solver.check_integrability(forms.faces, forms.edges, forms.lengths,
                                            forms.angles, tol=options.integrability_tol,
                                            n_vertices=n_vertices, vertex_map=forms.vertex_map,
                                            weld_map=forms.weld_map)
        if not report.integrable:
            raise _not_integrable(report)
    # reconstruct_vjp reads the options of reconstruct as its keywords; a real file's forms
    # (vertex_map, weld_map) are differentiated per file vertex, as reconstruct answers.
    result, vjp = solver.reconstruct_vjp(
        forms.faces, forms.edges, forms.lengths, forms.angles,
        constraints=_constraints(params.get("constraints")), n_vertices=n_vertices,
        progress=progress, vertex_map=forms.vertex_map, placement=forms.placement,
        weld_map=forms.weld_map, **dataclasses.asdict(options))
    cotangents = vjp.cotangents(np.asarray(params["cotangent"], dtype=np.float64))
    document = {"vertices": result.vertices, "faces": _file_faces(forms),
                "grad_lengths": cotangents.lengths, "grad_angles": cotangents.angles,
                "grad_positions": cotangents.positions, "grad_frames": cotangents.frames,
                "report": result.report.to_dict()}
    return _finish(request, progress, document)


def deform_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """Deform a mesh with position handles (and optional rotation handles / ROI)."""
    params = request.params
    progress("validate", 0.0)
    vertices, faces, read = _mesh_and_input(request)
    handles = params["handles"]
    rotations = params.get("rotations") or []
    roi = params.get("roi")
    result = solver.deform(
        vertices, faces, np.array([h["vertex"] for h in handles], dtype=np.int64),
        np.array([h["position"] for h in handles], dtype=np.float64).reshape(-1, 3),
        rotation_handles=[np.asarray(r["faces"], dtype=np.int64) for r in rotations] or None,
        handle_rotations=(np.array([r["rotation"] for r in rotations], dtype=np.float64)
                          if rotations else None),
        roi=None if roi is None else np.asarray(roi, dtype=np.int64),
        options=request.solve_options(solver.DeformOptions), progress=progress)
    distortion = (result.report.get("distortion") or {}).get("vertex")
    colors = {} if distortion is None else {"distortion": np.asarray(distortion)}
    document = {"vertices": result.vertices, "faces": faces,
                "report": _with_input(result.report.to_dict(), read)}
    return _finish(request, progress, document, (result.vertices, faces), colors)


def parameterize_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """Flatten a mesh (charts cut and packed where needed); glTF output is the 3D mesh with
    its seam vertices duplicated and the atlas as ``TEXCOORD_0``."""
    progress("validate", 0.0)
    vertices, faces, read = _mesh_and_input(request)
    result = solver.parameterize(vertices, faces,
                                 options=request.solve_options(solver.ParameterizeOptions),
                                 progress=progress)
    document = {"uv": result.uv, "flipped_faces": result.flipped_faces,
                "report": _with_input(result.report.to_dict(), read), "texcoords": result.texcoords,
                "uv_faces": result.uv_faces, "uv_vertex": result.uv_vertex,
                "face_chart": result.face_chart}
    textured = np.asarray(vertices, dtype=np.float64)[result.uv_vertex]
    return _finish(request, progress, document, (textured, result.uv_faces),
                   texcoords=result.texcoords)


def interpolate_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """Blend two embeddings of one connectivity in form space for one or several t."""
    params = request.params
    progress("validate", 0.0)
    source = request.source
    if isinstance(source, tuple):  # two uploads
        vertices_a, faces = _load_file(source[0], request)
        vertices_b, faces_b = _load_file(source[1], request)
        if faces_b.shape != faces.shape or not np.array_equal(faces, faces_b):
            raise ProblemError("shape-mismatch", "file_b must have the same faces as file_a",
                               errors=[element_error("file_b", "faces differ from file_a's")])
        check_work(params, request.limits, n_vertices=len(vertices_a))
    else:
        assert isinstance(source, MeshPair)
        vertices_a, vertices_b, faces = source.vertices_a, source.vertices_b, source.faces
    t = params["t"]
    if isinstance(t, list) and request.output.format != "json":
        raise ProblemError("not-acceptable", "glTF holds one mesh: request a single t, or "
                           "Accept: application/json for a list of t")
    progress("solve", 0.0)
    vertices, reports = solver.interpolate(
        vertices_a, vertices_b, faces, t, options=request.solve_options(solver.InterpolateOptions),
        return_reports=True)
    faces = np.asarray(faces)
    document = {"t": t, "vertices": vertices, "faces": faces,
                "refinement": reports[0] if np.ndim(t) == 0 else reports}
    mesh = (vertices, faces) if np.ndim(t) == 0 else None
    return _finish(request, progress, document, mesh)


def _same_faces(uploads: tuple[MeshFile, ...], request: TaskRequest
                ) -> tuple[list[np.ndarray], np.ndarray]:
    """The vertices of several uploads of one connectivity, and their faces."""
    loaded = [_load_file(upload, request) for upload in uploads]
    faces = loaded[0][1]
    for upload, (_, other) in zip(uploads[1:], loaded[1:], strict=True):
        if other.shape != faces.shape or not np.array_equal(other, faces):
            raise ProblemError("shape-mismatch", f"{upload.field} must have the same faces as "
                               f"{uploads[0].field}", errors=[element_error(
                                   upload.field, f"faces differ from {uploads[0].field}'s")])
    return [vertices for vertices, _ in loaded], faces


def _blend_weights(params: dict[str, Any], count: int) -> Any:
    """The rows of weights of a blend request: ``weights``, or ``(1 - t, t)`` of ``t``."""
    if params.get("weights") is not None:
        return params["weights"]
    if count != 2:
        raise ProblemError("validation-error", f"`t` blends two shapes; {count} were sent: "
                           "give `weights` (one per shape)",
                           errors=[element_error("t", "two shapes only")])
    from solver.interpolate import two_shape_weights

    return two_shape_weights(params["t"])


def blend_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """Blend K embeddings of one connectivity in form space, one shape per row of weights.
    JSON answers every row; glTF answers one animated file (each row a morph target, an
    animation that plays them at ``times``)."""
    params = request.params
    progress("validate", 0.0)
    source = request.source
    if isinstance(source, tuple):  # uploads: one `shapes` part per mesh
        shapes, faces = _same_faces(source, request)
        check_work(params, request.limits, n_vertices=len(shapes[0]))
    else:
        assert isinstance(source, MeshStack)
        shapes, faces = list(source.shapes), source.faces
    weights = _blend_weights(params, len(shapes))
    result = solver.blend(shapes, weights, faces,
                          options=request.solve_options(solver.BlendOptions),
                          progress=progress)
    document = {"weights": result.weights, "vertices": result.vertices, "faces": result.faces,
                "reports": result.reports, "warnings": result.warnings}
    out = request.output
    formats = ("glb", "gltf") if out.keep else (out.format,) if out.format != "json" else ()
    encoded = {}
    if formats:
        progress("encode", 0.0)
        try:
            extras = {"warnings": result.warnings} if result.warnings else None
            encoded = {fmt: gltf.encode_gltf_animation(
                result.vertices, result.faces, base=shapes[0], times=params.get("times"),
                kind=fmt, extras=extras) for fmt in formats}
        except solver.SolverInputError as exc:  # times of the wrong length or order
            raise ProblemError("validation-error", f"times: {exc}", errors=[element_error(
                "times", str(exc))]) from None
    if out.format != "json":
        progress("encode", 1.0)
        return TaskResult(output.MEDIA_TYPES[out.format], encoded[out.format],
                          encoded=encoded)
    finished = _finish(request, progress, document)
    finished.encoded = encoded
    return finished


def transfer_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """Deformation transfer: ``target`` deformed as ``source`` was into ``source_deformed``."""
    progress("validate", 0.0)
    source = request.source
    if isinstance(source, tuple):  # uploads: source, source_deformed, target
        (a, a2, b), faces = _same_faces(source, request)
    else:
        assert isinstance(source, MeshTriple)
        a, a2, b, faces = source.source, source.source_deformed, source.target, source.faces
    vertices, report = solver.transfer(a, a2, b, faces, return_report=True,
                                       options=request.solve_options(solver.BlendOptions),
                                       progress=progress)
    faces = np.asarray(faces)
    document = {"vertices": vertices, "faces": faces, "report": report}
    return _finish(request, progress, document, (vertices, faces))


def mesh_task(request: TaskRequest, progress: Progress) -> TaskResult:
    """A mesh file (or JSON mesh) read and checked: vertices in file order, faces, a summary.

    The connectivity is validated like every other operation does it (index range,
    manifoldness, orientation), so a viewer learns early why a mesh will not work.
    """
    from solver.reports import mesh_summary

    progress("validate", 0.0)
    vertices, faces, read = _mesh_and_input(request)
    progress("solve", 0.0)
    vertices, faces, report = mesh_summary(vertices, faces)
    document = {"vertices": vertices, "faces": faces, "report": _with_input(report, read)}
    return _finish(request, progress, document, (vertices, faces))


# ---------------------------------------------------------------------- test-only tasks


def _debug_sleep(request: TaskRequest, progress: Progress) -> TaskResult:
    """Sleep ``params["seconds"]`` reporting progress in ``params["steps"]`` steps, then 1."""
    steps = max(1, int(request.params.get("steps", 10)))
    for i in range(steps):
        progress("solve", i / steps)
        time.sleep(float(request.params.get("seconds", 1.0)) / steps)
    progress("solve", 1.0)
    return TaskResult("application/json", b'{"slept": true}')


def _debug_crash(request: TaskRequest, progress: Progress) -> TaskResult:
    """The worker process dies abruptly (exit code ``params["code"]``)."""
    import os

    progress("solve", 0.0)
    os._exit(int(request.params.get("code", 3)))


def _debug_raise(request: TaskRequest, progress: Progress) -> TaskResult:
    """An unexpected exception (a bug)."""
    raise RuntimeError(str(request.params.get("message", "boom")))


DEBUG_TASKS: dict[str, TaskFn] = {"debug.sleep": _debug_sleep, "debug.crash": _debug_crash,
                                  "debug.raise": _debug_raise}
"""Tasks for the tests of the backends (``TaskRequest.task``); not reachable over HTTP."""
