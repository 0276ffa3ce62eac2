"""Asynchronous jobs: submit (JSON or multipart upload), poll, fetch the result, cancel."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any, Literal

import anyio
from fastapi import APIRouter, Path, Query, Request
from starlette.responses import JSONResponse, Response

from service.access.quotas import CONCURRENT_JOBS
from service.api.documents import JobStatus
from service.api.problems import ProblemError, element_error
from service.api.schemas import ColorField
from service.api.task import TaskResult
from service.backends.contracts import JobService
from service.backends.errors import ClientJobsError
from service.backends.jobs import Job
from service.http.auth import Caller, CallerDep, quota_problem
from service.http.dependencies import JobsDep, ParserDep, SettingsDep
from service.http.negotiation import MESH_FORMATS
from service.http.openapi import created, error_responses, jobs_body
from service.http.payloads import job_submission
from service.http.routes import API_PREFIX, model_response, path_to
from service.http.routes.operations import check_color, format_query, formats, result_format
from service.http.webhooks import callback_target, follow_job
from service.operations import OPERATIONS
from service.worker.output import (
    MEDIA_TYPES,
    colors_for,
    json_bytes,
    mesh_bytes,
    with_colors,
)

router = APIRouter(prefix=API_PREFIX, tags=["jobs"])

JobId = Annotated[str, Path(description="Job id (from the Location header).")]
ColorQuery = Annotated[ColorField | None, Query(
    description="Add a per-vertex colour ramp of this field (a job precomputed with `color`): "
                "`defect` (reconstruct: the integrability defect) or `distortion` (deform). "
                "glTF gets COLOR_0, JSON a `colors` array.")]
FormatQuery = format_query(MESH_FORMATS)
MeshFormatQuery = Annotated[Literal["glb", "gltf"], Query(
    alias="format", description="`glb`: `model/gltf-binary` (default), `gltf`: "
                                "`model/gltf+json` (the buffer as a data URI).")]
GLTF_FILES = {"model/gltf-binary": {"schema": {"type": "string", "format": "binary"}},
              "model/gltf+json": {"schema": {"type": "string", "format": "binary"}}}

_RESULT_CONTENT = {
    "application/json": {"schema": {"type": "object", "description": "The body the "
                                    "synchronous endpoint of the job's operation returns."}},
    "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}},
    "model/gltf+json": {"schema": {"type": "object"}},
}


def _iso(timestamp: float | None) -> str | None:
    if timestamp is None:
        return None
    return datetime.fromtimestamp(timestamp, UTC).isoformat(timespec="milliseconds").replace(
        "+00:00", "Z")


def job_document(job: Job) -> JobStatus:
    """The document of ``GET /v1/jobs/{id}``.

    Args:
        job: The job's record.

    Returns:
        Its state, progress, timings and links; a failure as its problem document.
    """
    base = path_to(router, "get_job", job_id=job.id)
    return JobStatus(
        id=job.id, operation=job.operation, status=job.status,
        progress={"stage": job.stage, "fraction": round(job.fraction, 4),
                  "stages": dict(job.stages), "refinement": job.refinement},
        timings=dict(job.timings),
        created_at=_iso(job.created_at), started_at=_iso(job.started_at),
        finished_at=_iso(job.finished_at), expires_at=_iso(job.expires_at),
        error=_failure_document(job),
        links={"self": base, "result": path_to(router, "get_result", job_id=job.id)})


def _failure_document(job: Job) -> dict[str, Any] | None:
    """The problem document of a failed job's failure (its instance the job), or None."""
    if job.error is None:
        return None
    return ProblemError.from_dict(job.error).to_dict(path_to(router, "get_job", job_id=job.id))


def _status_response(job: Job, status_code: int = 200,
                     headers: dict[str, str] | None = None) -> Response:
    return model_response(job_document(job), status_code, headers)


async def _get(jobs: JobsDep, job_id: str, caller: Caller) -> Job:
    """The job, if ``caller`` may see it (404 for an unknown job and another key's alike)."""
    job = await jobs.get(job_id)
    if job is None or not caller.sees(job.owner):
        raise ProblemError("not-found", f"no job {job_id!r} (it may have expired)")
    return job


@router.post("/jobs", status_code=202, response_model=JobStatus, summary="Submit a job",
             description="Queues an operation and answers 202 with Location: /v1/jobs/{id}. "
                         "JSON: `{\"operation\", \"input\", \"color\"?}` where `input` is the "
                         "body the synchronous endpoint takes. Multipart: form fields "
                         "`operation`, optional `color`, the mesh in `file` (`file_a`/`file_b` "
                         "for interpolate) and the operation's other fields JSON-encoded.",
             response_class=JSONResponse, openapi_extra=jobs_body(), operation_id="submit_job",
             responses={202: created("Accepted; poll the Location.",
                                     f"{API_PREFIX}/jobs/{{id}}", "job_id",
                                     {"GetJob": "get_job", "GetJobResult": "get_job_result",
                                      "DeleteJob": "delete_job"}),
                        **error_responses(400, 408, 413, 415, 422, 429, 503)})
async def submit_job(request: Request, settings: SettingsDep, jobs: JobsDep,
                     parser: ParserDep, caller: CallerDep) -> Response:
    head, task = await job_submission(request, settings, parser)
    color, callback = head.color, callback_target(request, head.callback_url, caller)
    check_color(OPERATIONS[task.operation], color)
    task = task.with_deadline(settings.job_timeout)  # refinement stops in time (a result)
    try:
        job = await jobs.submit(task, color=color, owner=caller.owner,
                                max_per_owner=caller.concurrent_jobs)
    except ClientJobsError as exc:
        if caller.key is None:
            raise
        raise quota_problem(caller, CONCURRENT_JOBS, exc.limit, "jobs queued or running"
                            ) from None
    if callback is not None:
        follow_job(request, jobs, job.id, callback, caller, job_document)
    return _status_response(job, 202, {"Location": path_to(router, "get_job", job_id=job.id)})


@router.get("/jobs/{job_id}", response_model=JobStatus, summary="Job status",
            operation_id="get_job",
            description="State, progress by stage with fractions, timings and the error "
                        "(a problem document) of a job.",
            response_class=JSONResponse, responses=error_responses(404, 410, 422))
async def get_job(jobs: JobsDep, job_id: JobId, caller: CallerDep) -> Response:
    return _status_response(await _get(jobs, job_id, caller))


@router.get("/jobs/{job_id}/result", summary="Job result", operation_id="get_job_result",
            description="The result with the same content negotiation as the synchronous "
                        "endpoint (JSON, GLB, glTF; `?color=`). 409 while the job is not "
                        "finished, or when it failed or was cancelled.",
            response_class=Response,
            responses={200: {"description": "The result.", "content": _RESULT_CONTENT},
                       **error_responses(404, 406, 409, 410, 422)})
async def get_result(request: Request, jobs: JobsDep, job_id: JobId, caller: CallerDep,
                     color: ColorQuery = None, fmt: FormatQuery = None) -> Response:
    job = await _get(jobs, job_id, caller)
    return await _result(job, result_format(request, formats(OPERATIONS[job.operation]), fmt),
                         color, jobs)


@router.get("/jobs/{job_id}/mesh", summary="Job result as a glTF file",
            operation_id="get_job_mesh",
            description="The mesh of a finished job as GLB (default) or glTF: the bytes of "
                        "`GET /v1/jobs/{id}/result?format=glb|gltf`, declared as a file "
                        "download alone (generated clients read one media type per "
                        "response). 406 when the result is not a single mesh.",
            response_class=Response,
            responses={200: {"description": "The mesh file.", "content": GLTF_FILES},
                       **error_responses(404, 406, 409, 410, 422)})
async def get_mesh(jobs: JobsDep, job_id: JobId, caller: CallerDep,
                   color: ColorQuery = None, fmt: MeshFormatQuery = "glb") -> Response:
    job = await _get(jobs, job_id, caller)
    if not OPERATIONS[job.operation].mesh_result:
        raise ProblemError("not-acceptable", f"a {job.operation} job has no mesh result; use "
                           f"GET {path_to(router, 'get_result', job_id=job.id)}",
                           available=["application/json"])
    return await _result(job, fmt, color, jobs)


async def _result(job: Job, fmt: str, color: str | None, jobs: JobService) -> Response:
    """The result of ``job`` in format ``fmt``, or the problem saying why there is none."""
    spec = OPERATIONS[job.operation]
    check_color(spec, color)
    if job.status in ("queued", "running"):
        raise ProblemError("job-not-finished", f"job {job.id} is {job.status}",
                           headers={"Retry-After": "1"}, job_status=job.status)
    if job.status == "cancelled":
        raise ProblemError("job-cancelled", f"job {job.id} was cancelled")
    if job.status == "failed":
        error = _failure_document(job)
        raise ProblemError("job-failed", f"job {job.id} failed: "
                           f"{(error or {}).get('detail', 'no result')}", error=error)
    result = await jobs.result(job)
    values = None
    if color is not None:
        values = result.colors.get(color)
        if values is None:
            raise ProblemError(
                "color-not-computed",
                f"job {job.id} was submitted without \"color\": \"{color}\"; submit it with "
                "that field to get this colour",
                errors=[element_error("color", "not computed")])
    body = await anyio.to_thread.run_sync(_encode, result, fmt, values)
    return Response(body, media_type=MEDIA_TYPES[fmt])


def _encode(result: TaskResult, fmt: str, values: Any) -> bytes:
    if fmt == "json":
        return result.body if values is None else with_colors(result.body, colors_for(values))
    if fmt in result.encoded:  # an animated blend, encoded when it finished
        return result.encoded[fmt]
    if result.mesh is None:
        raise ProblemError("not-acceptable", "this result is not a single mesh; use "
                           "format=json or Accept: application/json")
    return mesh_bytes(fmt, result.mesh[0], result.mesh[1], values, result.texcoords)


@router.delete("/jobs/{job_id}", response_model=JobStatus, summary="Cancel or delete a job",
               operation_id="delete_job",
               description="Cancels a queued or running job (200, status `cancelled`; a "
                           "running solve is stopped by replacing its worker). A finished "
                           "job is deleted with its result (204).",
               response_class=JSONResponse,
               responses={204: {"description": "Deleted."},
                          **error_responses(404, 410, 422)})
async def delete_job(jobs: JobsDep, job_id: JobId, caller: CallerDep) -> Response:
    job = await _get(jobs, job_id, caller)
    if job.done:
        await jobs.delete(job)
        return Response(status_code=204)
    await jobs.cancel(job)
    return _status_response(job)


@router.get("/jobs", response_model=list[JobStatus], summary="List jobs",
            operation_id="list_jobs",
            description="The caller's stored jobs (queued, running, and finished ones until "
                        "they expire), oldest first: those of its API key (an admin key: "
                        "every key's), or without keys those submitted from its address.",
            response_class=JSONResponse)
async def list_jobs(jobs: JobsDep, caller: CallerDep) -> Response:
    owner = None if caller.is_admin else caller.owner  # keys off: the caller's address
    found = await jobs.list(owner)
    return Response(json_bytes([job_document(j).model_dump(exclude_unset=True)
                                for j in found]), media_type="application/json")
