"""Pydantic v2 models of what the API answers: results, job and session documents,
problem documents, health. They produce the OpenAPI document's response schemas (the
bodies themselves are encoded by the workers, :mod:`service.worker.output`); every model
carries an example.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from service.api.schemas import (
    EXAMPLE_FORMS,
    EXAMPLE_MESH,
    STOP_REASONS_TEXT,
    JobState,
    Operation,
    StopReasonName,
    Tri,
    Vec3,
)


class SessionInfo(BaseModel):
    """A deformation session."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"id": "9b2f4c1d8e7a4f6b8c0d1e2f3a4b5c6d", "n_vertices": 5, "n_faces": 4,
         "handles": [0, 1, 2, 3, 4], "n_rotation_groups": 0, "expires_in": 600.0,
         "setup_seconds": 0.004, "backend": "pardiso", "executor": "local",
         "memory_bytes": 92274688, "solves": 0, "refine": False,
         "links": {"self": "/v1/sessions/9b2f4c1d8e7a4f6b8c0d1e2f3a4b5c6d",
                   "solve": "/v1/sessions/9b2f4c1d8e7a4f6b8c0d1e2f3a4b5c6d/solve",
                   "ws": "/v1/sessions/9b2f4c1d8e7a4f6b8c0d1e2f3a4b5c6d/ws"}}]})

    id: str
    n_vertices: int
    n_faces: int
    handles: list[int] = Field(description="Handle vertices, in the order of "
                                           "`handle_positions`.")
    n_rotation_groups: int
    expires_in: float = Field(description="Seconds until the session expires unless it "
                                          "solves again.")
    setup_seconds: float = Field(description="Time to assemble and factorize.")
    backend: str = Field(description="Sparse factorization backend.")
    executor: Literal["local", "dask"] = Field(description="Where the session lives.")
    memory_bytes: int = Field(description="Memory the session holds (counts towards "
                                          "FFS_MAX_SESSION_MEMORY).")
    solves: int
    refine: bool = Field(False, description="Progressive drags (`options.refine: true`): "
                                            "each answers its linear shape at once and its "
                                            "refined shape when ready.")
    links: dict[str, str]


class SessionVertices(BaseModel):
    """Result of a session solve in JSON: the deformed vertices in input order."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"vertices": EXAMPLE_MESH["vertices"]}]})

    vertices: list[Vec3]
    shape: Literal["linear", "refined"] | None = Field(
        None, description="A progressive session's answers only: which shape this is.")
    drag: int | None = Field(None, description="A progressive session's answers only: the "
                                               "drag's number in the session (1, 2, ...).")
    refinement: SessionRefinement | None = Field(
        None, description="The refined shape only: how it refined.")


class SessionRefinement(BaseModel):
    """How a progressive session refined a drag (summed over its slices)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"converged": True, "stop_reason": "converged", "iterations": 4, "factorizations": 2,
         "slices": 3, "seconds": 0.21, "elapsed": 0.23, "energy": 1.2e-5,
         "start": "previous drag"}]})

    converged: bool
    stop_reason: StopReasonName = Field(description=(
        f"Why it stopped. {STOP_REASONS_TEXT} A drag's time budget is "
        "options.max_seconds or FFS_SESSION_SOLVE_TIMEOUT."))
    iterations: int
    factorizations: int
    slices: int = Field(description="Slices it ran in (FFS_SESSION_REFINE_SLICE each).")
    seconds: float = Field(description="Seconds spent refining.")
    elapsed: float = Field(description="Seconds from the linear answer to the refined one.")
    energy: float | None = Field(None, description="Energy of the refined shape.")
    start: str | None = Field(None, description="What the refinement started from.")


class RefiningStatus(BaseModel):
    """A drag whose refined shape is not ready yet (202)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"drag": 3, "status": "refining",
         "links": {"self": "/v1/sessions/9b2f4c1d8e7a4f6b8c0d1e2f3a4b5c6d/drags/3/refined"}}]})

    drag: int
    status: Literal["refining"]
    links: dict[str, str]


# --------------------------------------------------------------------------- responses


class FormsResponse(BaseModel):
    """Result of ``POST /v1/forms``; a valid body for /v1/integrability and /v1/reconstruct."""

    model_config = ConfigDict(json_schema_extra={"examples": [EXAMPLE_FORMS]})

    faces: list[Tri]
    edges: list[Annotated[list[int], Field(min_length=2, max_length=2)]]
    lengths: list[float]
    angles: list[float]
    vertex_map: list[int] | None = Field(
        None, description="Present for a non-manifold mesh, whose forms are those of its "
                          "manifold cut (`faces` are the cut faces): the file vertex of each "
                          "cut vertex. Send it back with the forms.")
    weld_map: list[int] | None = Field(
        None, description="Present when vertices joined by zero-length edges were welded: "
                          "the file vertex each file vertex was welded into (itself unless "
                          "welded). Send it back with the forms and `vertex_map`.")
    dropped_faces: list[int] | None = Field(
        None, description="Present when faces repeat a vertex once welded: those file faces, "
                          "left out of `faces` (informational).")
    placement: dict[str, Any] | None = Field(
        None, description="Each connected component's rigid placement (`faces`, `origins`, "
                          "`frames`): `reconstruct` puts every part back where it was.")
    zero_area_faces: list[int] | None = Field(
        None, description="Present when some faces have zero area (collinear corners): "
                          "those faces. Such a face has no normal of its own; it gets the "
                          "normalized sum of its neighbours' normals, projected off its line, "
                          "so the forms stay integrable (docs/service.md, 'Meshes as they "
                          "come').")


class HolonomyLoop(BaseModel):
    """One homology generator of the global integrability check."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"kind": "rotation", "component": 0, "edge": [3, 7], "faces": [4, 9], "edge_index": 12,
         "angle": 0.0, "translation": [0.0, 0.0, 0.0], "magnitude": 0.0, "passes": True}]})

    kind: Literal["rotation", "translation"]
    component: int
    edge: list[int] = Field(description="[i, j], the edge that closes the loop.")
    faces: list[int]
    edge_index: int = Field(description="Row of that edge in the sorted edge list.")
    angle: float
    translation: list[float]
    magnitude: float
    passes: bool


class ComponentSummary(BaseModel):
    """Topology of one connected component."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"component": 0, "vertices": 5, "edges": 8, "faces": 4, "boundary_loops": 1,
         "euler_characteristic": 1, "genus": 0, "closed": False}]})

    component: int
    vertices: int
    edges: int
    faces: int
    boundary_loops: int
    euler_characteristic: int
    genus: int
    closed: bool


class Topology(BaseModel):
    """Components, boundary loops and genus of the mesh."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"n_components": 1, "euler_characteristic": 1, "genus": 0,
         "boundary_loops": [[0, 1, 2, 3]], "isolated_vertices": [],
         "components": ComponentSummary.model_config["json_schema_extra"]["examples"]}]})

    n_components: int
    euler_characteristic: int
    genus: int
    boundary_loops: list[list[int]]
    isolated_vertices: list[int]
    components: list[ComponentSummary]


class GlobalHolonomy(BaseModel):
    """Holonomy along the homology generators (non-empty for genus > 0 or several holes)."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"rotation": [],
                                                               "translation": []}]})

    rotation: list[HolonomyLoop]
    translation: list[HolonomyLoop]


class IntegrabilityResponse(BaseModel):
    """The integrability report."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "integrable": True, "local_integrable": True, "global_integrable": True,
        "max_defect": 5.2e-16, "tolerance": 1e-8,
        "vertex_defect": [0.0, 0.0, 0.0, 0.0, 5.2e-16],
        "gauss_defect": [0.0, 0.0, 0.0, 0.0, 3.7e-16],
        "codazzi_defect": [0.0, 0.0, 0.0, 0.0, 3.8e-16], "failing_vertices": [],
        "worst_vertices": [4], "triangle_violations": [],
        "topology": Topology.model_config["json_schema_extra"]["examples"][0],
        "global_holonomy": {"rotation": [], "translation": []}}]})

    integrable: bool
    local_integrable: bool
    global_integrable: bool
    max_defect: float
    tolerance: float
    vertex_defect: list[float]
    gauss_defect: list[float]
    codazzi_defect: list[float]
    failing_vertices: list[int]
    worst_vertices: list[int]
    triangle_violations: list[int]
    topology: Topology
    global_holonomy: GlobalHolonomy


_REPORT_EXAMPLE = {"integrability": {"integrable": True, "max_defect": 5.2e-16,
                                     "worst_vertices": [{"vertex": 4, "defect": 5.2e-16}],
                                     "rotation_holonomy": [], "translation_holonomy": [],
                                     "rotation_loop_count": 0, "translation_loop_count": 0,
                                     "failing_loop_count": 0},
                   "backend": "pardiso", "timings": {"validate": 0.002, "assemble": 0.008,
                                                     "factorize": 0.02, "solve": 0.001},
                   "warnings": []}


class AnswerWarningDocument(BaseModel):
    """A threshold the answer is past (``solver.core.warnings.AnswerWarning``)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"code": "length-error", "value": 1.308, "limit": 0.05,
         "message": "the largest edge-length error left is 130.8% of the edge's target "
                    "length (limit 5%)"}]})

    code: str = Field(description="The rule: flipped-faces, length-error, angle-error, "
                      "length-distortion, angle-distortion, packing-efficiency, "
                      "overlapping-layout, time-limit-no-progress (docs/service.md)")
    message: str = Field(description="One sentence for people, with units.")
    value: float = Field(description="What was measured, in the unit of `limit`.")
    limit: float = Field(description="The documented threshold it is past.")


class AnswerReport(BaseModel):
    """An operation's report: timings, backend, integrability, ``refinement`` (with its
    ``outcome``: converged, partial or not-refined, and ``outcome_text``), distortion, ...
    and ``warnings``: the documented thresholds the answer is past ([] for a good answer)."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [
        {"refinement": {"refined": True, "converged": False, "stop_reason": "time_limit",
                        "iterations": 0, "outcome": "not-refined",
                        "outcome_text": "not refined: time limit before the first iteration"},
         "warnings": [{"code": "time-limit-no-progress", "value": 1.0, "limit": 1.0,
                       "message": "the time limit ran out after 0 refinement iterations, "
                                  "before any progress: the answer is the refinement's "
                                  "start (energy 80.27, unchanged); raise max_seconds"}]}]})

    warnings: list[AnswerWarningDocument] = Field(
        default_factory=list, description="Thresholds the answer is past (docs/service.md, "
        "Warnings); absent where the operation has no rules (mesh).")


class MeshResponse(BaseModel):
    """A mesh result (reconstruct, deform): vertices in input order, faces, and a report.

    With ``?color=...`` the JSON also carries ``colors`` (n, 4) linear RGBA.
    """

    model_config = ConfigDict(json_schema_extra={"examples": [
        {**EXAMPLE_MESH, "report": _REPORT_EXAMPLE}]})

    vertices: list[Vec3]
    faces: list[Tri]
    report: AnswerReport
    colors: list[Annotated[list[float], Field(min_length=4, max_length=4)]] | None = None


class ParameterizeResponse(BaseModel):
    """The flat layout ``uv`` over ``uv_faces`` (one uv per file vertex for one chart; a
    seam vertex once per chart it borders), the atlas in the unit square ``texcoords``,
    the file vertex of each uv (``uv_vertex``), the chart of each face, faces whose
    orientation flipped, and a report (``atlas``: charts, seams, packing; ``warnings``)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"uv": [[0.0, 0.0], [1.058, 0.0], [1.049, 1.04], [0.009, 1.04], [0.529, 0.543]],
         "flipped_faces": [], "report": {"flipped_count": 0, "backend": "pardiso"}}]})

    uv: list[Annotated[list[float], Field(min_length=2, max_length=2)]]
    flipped_faces: list[int]
    report: AnswerReport
    texcoords: list[Annotated[list[float], Field(min_length=2, max_length=2)]] | None = None
    uv_faces: list[Tri] | None = None
    uv_vertex: list[int] | None = None
    face_chart: list[int] | None = None


class InterpolateResponse(BaseModel):
    """Vertices per t: (n, 3) for a single t, (k, n, 3) for a list of k values."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"t": 0.5, **EXAMPLE_MESH}]})

    t: float | list[float]
    vertices: list[Vec3] | list[list[Vec3]]
    faces: list[Tri]
    refinement: dict[str, Any] | list[dict[str, Any]] | None = Field(
        None, description="Whether and how each blend was refined (nearest surface to the "
        "blended forms): one report for a single t, a list for a list of t.")


class BlendResponse(BaseModel):
    """One shape per row of weights, each the nearest surface to the blended forms."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"weights": [[0.5, 0.5]], "vertices": [EXAMPLE_MESH["vertices"]],
         "faces": EXAMPLE_MESH["faces"], "reports": [{"row": 0, "path": "reconstruct"}]}]})

    weights: list[list[float]] = Field(description="(T, K) the rows, as solved.")
    vertices: list[list[Vec3]] = Field(description="(T, n, 3) one shape per row, aligned "
                                       "rigidly to the row's vertex blend.")
    faces: list[Tri]
    reports: list[dict[str, Any]] = Field(
        description="Per row: `row`, `path` (`reconstruct` or `sequence`), `refinement`, "
        "`form_error` (length and angle errors against the blended forms), `warnings` "
        "(thresholds the row's answer is past), `seconds`.")
    warnings: list[dict[str, Any]] = Field(
        default_factory=list, description="Every row's warnings (`code`, `message`, "
        "`value`, `limit`), each with its `row`; [] when every row is within the documented "
        "thresholds (docs/service.md#warnings).")


class TransferResponse(BaseModel):
    """The target deformed as the source was."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {**EXAMPLE_MESH, "report": {"row": 0, "path": "reconstruct"}}]})

    vertices: list[Vec3]
    faces: list[Tri]
    report: dict[str, Any] = Field(description="`refinement`, `form_error` and `warnings` "
                                   "(thresholds the answer is past) of the answer.")


class ProblemItem(BaseModel):
    """One machine-readable pointer to what is wrong."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [
        {"field": "faces", "index": 17, "reason": "index 9001 out of range [0, 100)"}]})

    field: str | None = None
    index: int | None = None
    reason: str


class Problem(BaseModel):
    """RFC 9457 problem document (``application/problem+json``)."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [
        {"type": "/problems/index-out-of-range", "title": "Index out of range",
         "status": 422, "detail": "faces[17]: index 9001 out of range [0, 100)",
         "instance": "/v1/forms", "kind": "index-out-of-range",
         "errors": [{"field": "faces", "index": 17,
                     "reason": "index 9001 out of range [0, 100)", "value": 9001}]}]})

    type: str
    title: str
    status: int
    detail: str
    instance: str | None = None
    kind: str
    errors: list[ProblemItem] = Field(default_factory=list)


class RefinementProgress(BaseModel):
    """The refinement's last accepted step (a job's ``progress.refinement``)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"iteration": 2, "factorizations": 2, "energy": 3.1e-4, "seconds": 0.8}]})

    iteration: int = Field(description="Steps taken so far (1, 2, ...).")
    factorizations: int = Field(description="Sparse factorizations so far.")
    energy: float = Field(description="Energy after this step (it only decreases).")
    seconds: float = Field(description="Seconds since the refinement started.")


class JobProgress(BaseModel):
    """Progress of a job: the current stage, the fraction done of each stage and overall;
    during and after a refinement its last step."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"stage": "refine", "fraction": 0.7,
         "stages": {"validate": 1.0, "assemble": 1.0, "factorize": 1.0, "solve": 1.0,
                    "refine": 0.4, "encode": 0.0},
         "refinement": {"iteration": 2, "factorizations": 2, "energy": 3.1e-4,
                        "seconds": 0.8}}]})

    stage: str | None
    fraction: float
    stages: dict[str, float]
    refinement: RefinementProgress | None = Field(
        None, description="The refinement's last step, once it took one (null before, and "
                          "for operations that do not refine).")


class JobStatus(BaseModel):
    """State of an asynchronous job."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"id": "6f1c2b0e9a7d4c55b1f0e2d3c4b5a697", "operation": "reconstruct",
         "status": "running", "progress": JobProgress.model_config[
             "json_schema_extra"]["examples"][0],
         "timings": {"queued": 0.001, "validate": 0.01, "assemble": 0.05},
         "created_at": "2025-01-01T12:00:00.000Z", "started_at": "2025-01-01T12:00:00.001Z",
         "finished_at": None, "expires_at": None, "error": None,
         "links": {"self": "/v1/jobs/6f1c2b0e9a7d4c55b1f0e2d3c4b5a697",
                   "result": "/v1/jobs/6f1c2b0e9a7d4c55b1f0e2d3c4b5a697/result"}}]})

    id: str
    operation: Operation
    status: JobState
    progress: JobProgress
    timings: dict[str, float]
    created_at: str
    started_at: str | None
    finished_at: str | None
    expires_at: str | None
    error: Problem | None
    links: dict[str, str]


class SizeLimits(BaseModel):
    """How large a request the service admits (for the caller: its key's face quota
    included)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"max_vertices": 1888331, "max_faces": 3147219, "max_body_bytes": 314721900,
         "max_request_memory": 8392486092,
         "max_faces_by_operation": {"forms": 3147219, "reconstruct": 1062211,
                                    "deform": 767192},
         "max_sync_faces_by_operation": {"forms": 3147219, "reconstruct": 1011144},
         "max_direct_faces_by_operation": {"reconstruct": 767192},
         "max_linear_faces_by_operation": {"reconstruct": 1772309},
         "max_linear_sync_faces_by_operation": {"reconstruct": 1011144}}]})

    max_vertices: int = Field(description="FFS_MAX_VERTICES (413 beyond).")
    max_faces: int = Field(description="FFS_MAX_FACES (413 beyond).")
    max_body_bytes: int = Field(description="FFS_MAX_BODY_BYTES (413 beyond).")
    max_request_memory: int = Field(description="FFS_MAX_REQUEST_MEMORY: bytes one request "
                                                "may use in its worker.")
    max_faces_by_operation: dict[str, int] = Field(
        description="The most faces each operation takes: at most FFS_MAX_FACES, and at most "
                    "what its predicted peak memory fits in FFS_MAX_REQUEST_MEMORY "
                    "(`sessions`: a deformation session).")
    max_sync_faces_by_operation: dict[str, int] = Field(
        default_factory=dict,
        description="The most faces a synchronous request of each operation may bring: those "
                    "whose first answer is predicted within FFS_REQUEST_TIMEOUT (less the "
                    "margin for encoding it), at most `max_faces_by_operation`; beyond, 413 "
                    "`use-a-job`: submit it as a job.")
    max_direct_faces_by_operation: dict[str, int] = Field(
        default_factory=dict,
        description="For the operations whose solver may go iterative (`reconstruct`): the "
                    "most faces it solves by factorizations within FFS_MAX_REQUEST_MEMORY; "
                    "beyond, up to `max_faces_by_operation`, it runs the iterative path "
                    "(`options.linear_solver`: `auto`), which takes less memory and more "
                    "time.")
    max_linear_faces_by_operation: dict[str, int] = Field(
        default_factory=dict,
        description="For the same operations: the most faces of a request for the linear "
                    "answer (`options.refine`: false), whose iterative path takes less "
                    "memory per face than the refined answer's.")
    max_linear_sync_faces_by_operation: dict[str, int] = Field(
        default_factory=dict,
        description="For the same operations: the most faces a synchronous request for the "
                    "linear answer (`options.refine`: false) may bring, predicted like "
                    "`max_sync_faces_by_operation` by the linear answer's pricing; beyond, "
                    "413 `use-a-job`. A client that chooses between a synchronous request and "
                    "a job reads this one for a linear answer.")


class Caller(BaseModel):
    """``GET /v1/me``: whether the service has API keys, the caller's key, and the size
    limits of its requests."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"keys": True, "name": "alice", "role": "user",
         "limits": {"requests_per_minute": 600, "concurrent_jobs": 16,
                    "concurrent_sessions": 4, "max_faces": 500000},
         "size_limits": {"max_vertices": 300000, "max_faces": 500000,
                         "max_body_bytes": 67108864, "max_request_memory": 8392486092,
                         "max_faces_by_operation": {"forms": 500000,
                                                    "reconstruct": 500000}}}]})

    keys: bool = Field(description="Whether the service requires API keys.")
    name: str | None = Field(None, description="The key's name (with keys).")
    role: Literal["user", "admin"] | None = Field(None, description="The key's role.")
    limits: dict[str, int | None] | None = Field(None, description="The key's quotas.")
    size_limits: SizeLimits | None = Field(None, description="How large a request may be.")


class Health(BaseModel):
    """Liveness."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"status": "ok"}]})

    status: str


class Readiness(BaseModel):
    """Readiness: the worker pool is up."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"status": "ready", "workers": 2, "workers_ready": 2, "busy": 0, "queue_depth": 0}]})

    status: Literal["ready", "starting", "unavailable"]
    workers: int
    workers_ready: int
    busy: int
    queue_depth: int


class ProblemKind(BaseModel):
    """Description of one problem type."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"type": "/problems/queue-full", "kind": "queue-full", "status": 503,
         "title": "Server busy",
         "description": "The work queue is full; retry after Retry-After seconds."}]})

    type: str
    kind: str
    status: int
    title: str
    description: str
