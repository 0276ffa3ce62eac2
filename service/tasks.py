"""The functions that run in the worker processes.

Each task takes a payload dict (numpy arrays, bytes and JSON-able values; see
:func:`run`) and a ``progress(stage, fraction)`` callback, calls :mod:`solver`, and returns
a result dict::

    {"media_type": str, "body": bytes,               # the response in the requested format
     "mesh": {"vertices", "faces"} | None,            # with output.keep (jobs): for re-encoding
     "colors": {"defect" | "distortion": (n,)},       # with output.keep: per-vertex scalars
     "timings": {stage: seconds}}

Payload::

    {"source": {"kind": "arrays", "vertices", "faces"}              # a mesh
             | {"kind": "forms", "faces", "edges", "lengths", "angles"}
             | {"kind": "pair", "vertices_a", "vertices_b", "faces"}  # interpolate
             | {"kind": "file", "data": bytes, "filename": str}      # an uploaded mesh file
             | {"kind": "files", "a": {...}, "b": {...}},              # two uploads
     "params": {...},        # the operation's params model, dumped
     "limits": {"max_vertices": int, "max_faces": int},
     "backend": "auto",      # FFS_SOLVER_BACKEND, used when options.solver is not given
     "output": {"format": "json" | "glb" | "gltf", "color": None | "defect" | "distortion",
                "compute": [colour fields to compute], "keep": bool}}

Errors leave the worker as dicts (:func:`describe_error`), never as pickled exceptions.
Everything here is importable at top level so it pickles under ``spawn``/``forkserver``.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np

import solver
from service import output
from solver.errors import SolverInputError, TriangleInequalityError

Progress = Callable[[str, float], None]
TaskFn = Callable[[dict[str, Any], Progress], dict[str, Any]]

STAGES_SOLVE: tuple[str, ...] = ("validate", "assemble", "factorize", "solve", "refine",
                                  "encode")
STAGES_LIGHT: tuple[str, ...] = ("validate", "solve", "encode")
STAGES: dict[str, tuple[str, ...]] = {
    "forms": STAGES_LIGHT, "integrability": STAGES_LIGHT, "interpolate": STAGES_LIGHT,
    "reconstruct": STAGES_SOLVE, "deform": STAGES_SOLVE, "parameterize": STAGES_SOLVE,
    "mesh": STAGES_LIGHT,
}
"""Progress stages reported by each operation, in order."""

COLOR_FIELDS: dict[str, tuple[str, ...]] = {"reconstruct": ("defect",),
                                            "deform": ("distortion",)}
"""Vertex colour fields each operation can produce (``?color=``)."""

MESH_OPERATIONS: tuple[str, ...] = ("reconstruct", "deform", "parameterize", "interpolate",
                                     "mesh")
"""Operations whose result is a mesh (glTF can be requested)."""


class TaskProblemError(Exception):
    """A client-caused failure detected in a worker, with its problem kind and status."""

    def __init__(self, kind: str, status: int, detail: str,
                 errors: list[dict[str, Any]] | None = None, **extensions: Any) -> None:
        super().__init__(detail)
        self.kind, self.status, self.detail = kind, status, detail
        self.errors = errors or []
        self.extensions = extensions


def describe_error(exc: BaseException) -> dict[str, Any]:
    """A picklable description of a task failure (see ``problems.from_worker_error``)."""
    if isinstance(exc, SolverInputError):
        return {"category": "input", "error": exc.to_dict(), "message": str(exc)}
    if isinstance(exc, TaskProblemError):
        return {"category": "problem", "kind": exc.kind, "status": exc.status,
                "detail": exc.detail, "errors": exc.errors, "extensions": exc.extensions}
    from service.problems import ProblemError

    if isinstance(exc, ProblemError):  # e.g. a JSON body validated in the worker
        return {"category": "problem", "kind": exc.kind, "status": exc.status,
                "detail": exc.detail, "errors": exc.errors, "extensions": exc.extensions}
    mapped = _map_solver_exception(exc)
    if mapped is not None:
        return describe_error(mapped)
    return {"category": "internal", "exception": type(exc).__name__, "message": str(exc),
            "traceback": traceback.format_exc()}


def _map_solver_exception(exc: BaseException) -> TaskProblemError | None:
    """Client-caused solver failures that are not SolverInputErrors."""
    from solver import linalg

    if isinstance(exc, linalg.BackendUnavailableError):
        return TaskProblemError("invalid-option", 422, str(exc),
                                [{"field": "options.solver", "index": None, "reason": str(exc)}])
    if isinstance(exc, linalg.SingularSystemError):
        return TaskProblemError("singular-system", 422, f"the linear system is singular: {exc}",
                                [{"field": "constraints", "index": None, "reason": str(exc)}])
    if isinstance(exc, MemoryError):
        return TaskProblemError("mesh-too-large", 413,
                                "the input needs more memory than is available")
    return None


def release_memory() -> None:
    """Give freed heap memory back to the system (glibc ``malloc_trim``; a no-op elsewhere).

    Parsing a large JSON body allocates millions of small objects; once freed, glibc keeps
    the pages unless asked, so a process's RSS would stay at its largest body."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _malloc_trim() -> Any:
    global _TRIM
    if _TRIM is None:
        import ctypes
        import ctypes.util

        try:
            _TRIM = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _TRIM = False
    return _TRIM or None


_TRIM: Any = None


def initialize_worker(threads: int) -> None:
    """Warm a worker: load the sparse backends once and cap BLAS/MKL threads."""
    from solver import linalg

    linalg.available_backends()
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(threads)
    except Exception:  # threadpoolctl missing or a library it cannot control
        pass


class _Clock:
    """Wraps ``progress`` and measures the wall time of each stage."""

    def __init__(self, progress: Progress) -> None:
        self._progress = progress
        self.stage: str | None = None
        self._since = time.perf_counter()
        self.timings: dict[str, float] = {}

    def __call__(self, stage: str, fraction: float) -> None:
        self._lap(stage)
        self._progress(stage, fraction)

    def _lap(self, stage: str | None) -> None:
        now = time.perf_counter()
        if stage != self.stage:
            if self.stage is not None:
                self.timings[self.stage] = self.timings.get(self.stage, 0.0) + now - self._since
            self.stage, self._since = stage, now

    def finish(self) -> dict[str, float]:
        self._lap(None)
        return self.timings


def run(fn_name: str, payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Run task ``fn_name`` with stage timing; the entry point used by the workers.

    A raw body (``source.kind`` ``json`` or ``binary``) is parsed and validated here first,
    as part of the ``validate`` stage (:func:`service.inputs.expand_body`)."""
    fn = TASKS[fn_name]
    clock = _Clock(progress)
    source = payload.get("source")
    if isinstance(source, dict) and source.get("kind") in ("json", "binary"):
        from service.inputs import expand_body

        clock("validate", 0.0)
        payload = expand_body(fn_name, payload)
    result = fn(payload, clock)
    result["timings"] = clock.finish()
    return result


# ------------------------------------------------------------------------------ inputs


def _load_file(upload: dict[str, Any], limits: dict[str, int], field: str = "file",
               ) -> tuple[np.ndarray, np.ndarray]:
    from solver.io import MeshFileError, UnsupportedFormatError, load_mesh

    try:
        vertices, faces = load_mesh(upload["data"], upload["filename"])
    except UnsupportedFormatError as exc:
        raise TaskProblemError("unsupported-file-type", 415, str(exc),
                               [{"field": field, "index": None, "reason": exc.reason}]) from exc
    except MeshFileError as exc:
        raise TaskProblemError("unreadable-file", 400, f"{upload['filename']}: {exc}",
                               [{"field": field, "index": None, "reason": exc.reason,
                                 **exc.details}]) from exc
    check_limits(len(vertices), len(faces), limits, field)
    return vertices, faces


def check_limits(n_vertices: int, n_faces: int, limits: dict[str, int], field: str) -> None:
    """Raise a 413 ``mesh-too-large`` problem beyond the vertex or face limit."""
    errors = []
    if n_vertices > limits["max_vertices"]:
        errors.append({"field": field, "index": None,
                       "reason": f"{n_vertices} vertices exceed the limit of "
                                 f"{limits['max_vertices']}"})
    if n_faces > limits["max_faces"]:
        errors.append({"field": field, "index": None,
                       "reason": f"{n_faces} faces exceed the limit of {limits['max_faces']}"})
    if errors:
        raise TaskProblemError("mesh-too-large", 413, errors[0]["reason"], errors)


def _mesh(payload: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    source = payload["source"]
    if source["kind"] == "file":
        return _load_file(source, payload["limits"])
    return source["vertices"], source["faces"]


def _forms(payload: dict[str, Any]) -> tuple[dict[str, Any], int | None]:
    """Forms from the payload (computed from the mesh for a file upload) and n_vertices."""
    source = payload["source"]
    if source["kind"] == "forms":
        return {k: source[k] for k in ("faces", "edges", "lengths", "angles")}, None
    vertices, faces = _mesh(payload)
    forms = solver.fundamental_forms(vertices, faces)
    return {"faces": forms.faces, "edges": forms.edges, "lengths": forms.lengths,
            "angles": forms.angles}, len(vertices)


def _backend(payload: dict[str, Any]) -> str:
    return payload["params"].get("options", {}).get("solver") or payload.get("backend", "auto")


def _finish(payload: dict[str, Any], progress: Progress, document: dict[str, Any],
            mesh: tuple[np.ndarray, np.ndarray] | None = None,
            colors: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """The encode stage: the response body in the requested format (+ kept data for jobs)."""
    progress("encode", 0.0)
    out = payload.get("output") or {}
    fmt, color = out.get("format", "json"), out.get("color")
    colors = colors or {}
    values = colors.get(color) if color else None
    if fmt == "json":
        if values is not None:
            document["colors"] = output.colors_for(values)
        body = output.json_bytes(document)
    else:
        if mesh is None:
            raise TaskProblemError("not-acceptable", 406, "this result is not a single mesh")
        body = output.mesh_bytes(fmt, mesh[0], mesh[1], values)
    result: dict[str, Any] = {"media_type": output.MEDIA_TYPES[fmt], "body": body}
    if out.get("keep"):
        result["mesh"] = None if mesh is None else {"vertices": mesh[0], "faces": mesh[1]}
        result["colors"] = colors
    progress("encode", 1.0)
    return result


def _wants(payload: dict[str, Any], field: str) -> bool:
    out = payload.get("output") or {}
    return out.get("color") == field or field in (out.get("compute") or ())


# ------------------------------------------------------------------------------- tasks


def forms_task(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Edge lengths and dihedral angles of a mesh."""
    progress("validate", 0.0)
    vertices, faces = _mesh(payload)
    progress("solve", 0.0)
    forms = solver.fundamental_forms(vertices, faces)
    document = {"faces": forms.faces, "edges": forms.edges, "lengths": forms.lengths,
                "angles": forms.angles}
    return _finish(payload, progress, document)


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
    }


def integrability_task(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """The integrability report of a set of forms (or of a mesh file's forms)."""
    progress("validate", 0.0)
    forms, n_vertices = _forms(payload)
    progress("solve", 0.0)
    report = solver.check_integrability(forms["faces"], forms["edges"], forms["lengths"],
                                        forms["angles"], tol=payload["params"]["tolerance"],
                                        n_vertices=n_vertices)
    return _finish(payload, progress, integrability_document(report))


def _not_integrable(report: solver.IntegrabilityReport) -> TaskProblemError:
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
    return TaskProblemError(
        "not-integrable", 422,
        f"the forms are not integrable: max defect {report.max_defect:.3g} (tolerance "
        f"{report.tolerance:g}); worst vertices {worst}", errors,
        worst_vertices=worst, integrability=report.summary())


def _constraints(data: dict[str, Any] | None) -> solver.Constraints | None:
    if not data:
        return None
    positions, frames = data.get("positions") or [], data.get("frames") or []
    if not positions and not frames:
        return None

    def weights(items: list[dict[str, Any]]) -> np.ndarray:
        return np.array([np.inf if c.get("weight") is None else c["weight"] for c in items],
                        dtype=np.float64)

    return solver.Constraints(
        position_vertices=np.array([c["vertex"] for c in positions], dtype=np.int64),
        positions=np.array([c["position"] for c in positions], dtype=np.float64).reshape(-1, 3),
        position_weights=weights(positions),
        frame_faces=np.array([c["face"] for c in frames], dtype=np.int64),
        frames=np.array([c["frame"] for c in frames], dtype=np.float64).reshape(-1, 3, 3),
        frame_weights=weights(frames))


def _number(value: float) -> str:
    """A float as the client most likely wrote it (``100``, ``1.41``)."""
    value = float(value)
    return str(int(value)) if value.is_integer() and abs(value) < 1e15 else repr(value)


def _quote_sent_lengths(exc: TriangleInequalityError, forms: dict[str, Any]
                        ) -> TriangleInequalityError:
    """The solver's triangle-inequality error (it sees lengths divided by the mean edge
    length) restated with the lengths as sent, and the edges they belong to."""
    t = exc.index
    if t is None:
        return exc
    faces, edges = np.asarray(forms["faces"]), np.asarray(forms["edges"])
    a, b, c = (int(v) for v in faces[t])
    pairs = np.sort(np.array([[a, b], [b, c], [c, a]]), axis=1)
    base = int(max(edges.max(), pairs.max())) + 1
    rows = np.searchsorted(edges[:, 0] * base + edges[:, 1], pairs[:, 0] * base + pairs[:, 1])
    sent = np.asarray(forms["lengths"])[rows]
    order = np.argsort(sent)
    quoted = [_number(v) for v in sent]
    longest, others = quoted[order[2]], [quoted[order[0]], quoted[order[1]]]
    count = len(exc.details.get("faces", [t]))
    return TriangleInequalityError(
        f"edge lengths {', '.join(quoted)} of face {t} (edges {pairs.tolist()}) violate the "
        f"triangle inequality: {longest} > {others[0]} + {others[1]}"
        + (f" ({count} faces in all)" if count > 1 else ""),
        field="faces", index=t,
        details={**exc.details, "edges": rows.tolist(), "lengths": sent.tolist()})


def reconstruct_task(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Vertex positions from forms; validates integrability first (see the API docs)."""
    params = payload["params"]
    options = params["options"]
    progress("validate", 0.0)
    forms, n_vertices = _forms(payload)
    full_report = None
    if options["require_integrable"] or _wants(payload, "defect"):
        full_report = solver.check_integrability(
            forms["faces"], forms["edges"], forms["lengths"], forms["angles"],
            tol=options["tolerance"], n_vertices=n_vertices)
        if options["require_integrable"] and not full_report.integrable:
            raise _not_integrable(full_report)
    try:
        result = solver.reconstruct(
            forms["faces"], forms["edges"], forms["lengths"], forms["angles"],
            constraints=_constraints(params.get("constraints")),
            frame_weight=options["frame_weight"], orthonormalize=options["orthonormalize"],
            orthonormal_weight=options["orthonormal_weight"], weighting=options["weighting"],
            backend=_backend(payload), n_vertices=n_vertices,
            check_integrability=full_report is None, integrability_tol=options["tolerance"],
            exact_shortcut=options["exact_shortcut"], refine=options["refine"],
            progress=progress)
    except TriangleInequalityError as exc:
        raise _quote_sent_lengths(exc, forms) from None
    report = dict(result.report)
    if full_report is not None:
        report = {"integrability": full_report.summary(), **report}
    faces = np.asarray(forms["faces"])
    colors = {"defect": full_report.vertex_defect} if full_report is not None else {}
    document = {"vertices": result.vertices, "faces": faces, "report": report}
    return _finish(payload, progress, document, (result.vertices, faces), colors)


def deform_task(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Deform a mesh with position handles (and optional rotation handles / ROI)."""
    params = payload["params"]
    options = params["options"]
    progress("validate", 0.0)
    vertices, faces = _mesh(payload)
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
        frame_weight=options["frame_weight"], orthonormalize=options["orthonormalize"],
        orthonormal_weight=options["orthonormal_weight"], weighting=options["weighting"],
        backend=_backend(payload), refine=options["refine"], progress=progress)
    distortion = (result.report.get("distortion") or {}).get("vertex")
    colors = {} if distortion is None else {"distortion": np.asarray(distortion)}
    document = {"vertices": result.vertices, "faces": faces, "report": result.report}
    return _finish(payload, progress, document, (result.vertices, faces), colors)


def parameterize_task(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Flatten a mesh with boundary; glTF output is the flat mesh (u, v, 0)."""
    options = payload["params"]["options"]
    progress("validate", 0.0)
    vertices, faces = _mesh(payload)
    result = solver.parameterize(
        vertices, faces, orthonormalize=options["orthonormalize"],
        orthonormal_weight=options["orthonormal_weight"], frame_weight=options["frame_weight"],
        weighting=options["weighting"], backend=_backend(payload), refine=options["refine"],
        progress=progress)
    document = {"uv": result.uv, "flipped_faces": result.flipped_faces, "report": result.report}
    flat = np.column_stack([result.uv, np.zeros(len(result.uv))])
    return _finish(payload, progress, document, (flat, np.asarray(faces)))


def interpolate_task(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Blend two embeddings of one connectivity in form space for one or several t."""
    params = payload["params"]
    options = params["options"]
    progress("validate", 0.0)
    source = payload["source"]
    if source["kind"] == "files":
        vertices_a, faces = _load_file(source["a"], payload["limits"], "file_a")
        vertices_b, faces_b = _load_file(source["b"], payload["limits"], "file_b")
        if faces_b.shape != faces.shape or not np.array_equal(faces, faces_b):
            raise TaskProblemError("shape-mismatch", 422,
                                   "file_b must have the same faces as file_a",
                                   [{"field": "file_b", "index": None,
                                     "reason": "faces differ from file_a's"}])
    else:
        vertices_a, vertices_b, faces = (source["vertices_a"], source["vertices_b"],
                                         source["faces"])
    t = params["t"]
    if isinstance(t, list) and (payload.get("output") or {}).get("format", "json") != "json":
        raise TaskProblemError("not-acceptable", 406, "glTF holds one mesh: request a single "
                               "t, or Accept: application/json for a list of t")
    progress("solve", 0.0)
    vertices, reports = solver.interpolate(
        vertices_a, vertices_b, faces, t, frame_weight=options["frame_weight"],
        weighting=options["weighting"], backend=_backend(payload), refine=options["refine"],
        return_reports=True)
    faces = np.asarray(faces)
    document = {"t": t, "vertices": vertices, "faces": faces,
                "refinement": reports[0] if np.ndim(t) == 0 else reports}
    mesh = (vertices, faces) if np.ndim(t) == 0 else None
    return _finish(payload, progress, document, mesh)


def mesh_task(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """A mesh file (or JSON mesh) read and checked: vertices in file order, faces, a summary.

    The connectivity is validated like every other operation does it (index range,
    manifoldness, orientation), so a viewer learns early why a mesh will not work.
    """
    from solver.topology import build_topology

    progress("validate", 0.0)
    vertices, faces = _mesh(payload)
    progress("solve", 0.0)
    topology = build_topology(faces, n_vertices=len(vertices))
    faces = topology.faces
    edges = topology.edges
    lengths = np.linalg.norm(vertices[edges[:, 1]] - vertices[edges[:, 0]], axis=1)
    report = {"n_vertices": len(vertices), "n_faces": len(faces), "n_edges": len(edges),
              "bounds": [vertices.min(axis=0), vertices.max(axis=0)],
              "mean_edge_length": float(lengths.mean()) if len(lengths) else 0.0}
    document = {"vertices": vertices, "faces": faces, "report": report}
    return _finish(payload, progress, document, (vertices, faces))


def _debug_sleep(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Test helper (not reachable over HTTP): sleep ``seconds`` reporting progress."""
    steps = max(1, int(payload.get("steps", 10)))
    for i in range(steps):
        progress("solve", i / steps)
        time.sleep(float(payload.get("seconds", 1.0)) / steps)
    return {"media_type": "application/json", "body": b'{"slept": true}'}


def _debug_crash(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Test helper (not reachable over HTTP): the worker process dies abruptly."""
    import os

    progress("solve", 0.0)
    os._exit(int(payload.get("code", 3)))


def _debug_raise(payload: dict[str, Any], progress: Progress) -> dict[str, Any]:
    """Test helper (not reachable over HTTP): an unexpected exception."""
    raise RuntimeError(str(payload.get("message", "boom")))


TASKS: dict[str, TaskFn] = {
    "forms": forms_task,
    "integrability": integrability_task,
    "reconstruct": reconstruct_task,
    "deform": deform_task,
    "parameterize": parameterize_task,
    "interpolate": interpolate_task,
    "mesh": mesh_task,
    "debug.sleep": _debug_sleep,
    "debug.crash": _debug_crash,
    "debug.raise": _debug_raise,
}
"""Task name -> function; only the seven operations are reachable over HTTP."""
