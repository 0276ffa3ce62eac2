"""Asynchronous jobs: submit (JSON or multipart upload), poll, fetch the result, cancel."""

from __future__ import annotations

from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Path, Request
from starlette.responses import Response

from service.inputs import (
    is_json,
    json_payload,
    media_type,
    off_loop,
    payload_from_form,
    read_body,
    read_form,
    unsupported_media_type,
    validate_object,
)
from service.jobs import Job
from service.negotiation import JSON_ONLY, MESH_FORMATS, negotiate
from service.openapi import error_responses, id_links, jobs_body
from service.output import MEDIA_TYPES, colors_for, json_bytes, mesh_bytes, with_colors
from service.problems import ProblemError
from service.routes.operations import ColorQuery, check_color
from service.schemas import JobRequest, JobStatus
from service.tasks import MESH_OPERATIONS
from service.validation import parse_json

router = APIRouter(tags=["jobs"])

JobId = Annotated[str, Path(description="Job id (from the Location header).")]

_RESULT_CONTENT = {
    "application/json": {"schema": {"type": "object", "description": "The body the "
                                    "synchronous endpoint of the job's operation returns."}},
    "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}},
    "model/gltf+json": {"schema": {"type": "object"}},
}


def _json_job(body: bytes, settings: Any) -> tuple[JobRequest, dict[str, Any]]:
    """(head, payload) of a JSON job: ``input`` is validated like the synchronous body (its
    arrays with numpy); in a thread for large bodies (:func:`off_loop`)."""
    head = validate_object(JobRequest, parse_json(body))
    limits = {"max_vertices": settings.max_vertices, "max_faces": settings.max_faces}
    return head, json_payload(head.operation, head.input, limits, settings.solver_backend,
                              prefix=("input",))


def _status_response(job: Job, status_code: int = 200,
                     headers: dict[str, str] | None = None) -> Response:
    return Response(json_bytes(job.to_status()), status_code=status_code,
                    media_type="application/json", headers=headers)


async def _get(request: Request, job_id: str) -> Job:
    job = await request.app.state.jobs.get(job_id)
    if job is None:
        raise ProblemError("not-found", f"no job {job_id!r} (it may have expired)")
    return job


@router.post("/v1/jobs", status_code=202, response_model=JobStatus, summary="Submit a job",
             description="Queues an operation and answers 202 with Location: /v1/jobs/{id}. "
                         "JSON: `{\"operation\", \"input\", \"color\"?}` where `input` is the "
                         "body the synchronous endpoint takes. Multipart: form fields "
                         "`operation`, optional `color`, the mesh in `file` (`file_a`/`file_b` "
                         "for interpolate) and the operation's other fields JSON-encoded.",
             response_class=Response, openapi_extra=jobs_body(), operation_id="submit_job",
             responses={202: {"description": "Accepted; poll the Location.",
                              "headers": {"Location": {"schema": {"type": "string"},
                                                       "description": "/v1/jobs/{id}"}},
                              "links": id_links("job_id", {
                                  "GetJob": "get_job", "GetJobResult": "get_job_result",
                                  "DeleteJob": "delete_job"})},
                        **error_responses(400, 408, 413, 415, 422, 503)})
async def submit_job(request: Request) -> Response:
    settings = request.app.state.settings
    mtype = media_type(request)
    if mtype == "multipart/form-data":
        fields, files = await read_form(request, settings)
        head = validate_object(JobRequest, {"operation": fields.pop("operation", None),
                                            "color": fields.pop("color", None), "input": {}})
        payload = await payload_from_form(head.operation, fields, files, settings)
    elif is_json(mtype):
        body = await read_body(request, settings)
        head, payload = await off_loop(len(body), _json_job, body, settings)
    else:
        raise unsupported_media_type(mtype)
    check_color(head.operation, head.color)
    payload["output"] = {"format": "json", "color": None,
                         "compute": [head.color] if head.color else [], "keep": True}
    job = await request.app.state.jobs.submit(head.operation, payload, color=head.color)
    return _status_response(job, 202, {"Location": f"/v1/jobs/{job.id}"})


@router.get("/v1/jobs/{job_id}", response_model=JobStatus, summary="Job status",
            operation_id="get_job",
            description="State, progress by stage with fractions, timings and the error "
                        "(a problem document) of a job.",
            response_class=Response, responses=error_responses(404, 422))
async def get_job(request: Request, job_id: JobId) -> Response:
    return _status_response(await _get(request, job_id))


@router.get("/v1/jobs/{job_id}/result", summary="Job result", operation_id="get_job_result",
            description="The result with the same content negotiation as the synchronous "
                        "endpoint (JSON, GLB, glTF; `?color=`). 409 while the job is not "
                        "finished, or when it failed or was cancelled.",
            response_class=Response,
            responses={200: {"description": "The result.", "content": _RESULT_CONTENT},
                       **error_responses(404, 406, 409, 422)})
async def get_result(request: Request, job_id: JobId, color: ColorQuery = None) -> Response:
    job = await _get(request, job_id)
    formats = MESH_FORMATS if job.operation in MESH_OPERATIONS else JSON_ONLY
    fmt = negotiate(request.headers.get("accept"), formats)
    check_color(job.operation, color)
    if job.status in ("queued", "running"):
        raise ProblemError("job-not-finished", f"job {job.id} is {job.status}",
                           headers={"Retry-After": "1"}, job_status=job.status)
    if job.status == "cancelled":
        raise ProblemError("job-cancelled", f"job {job.id} was cancelled")
    if job.status == "failed":
        raise ProblemError("job-failed", f"job {job.id} failed: "
                           f"{(job.error or {}).get('detail', 'no result')}", error=job.error)
    result = await request.app.state.jobs.result(job)
    values = None
    if color is not None:
        values = (result.get("colors") or {}).get(color)
        if values is None:
            raise ProblemError(
                "color-not-computed",
                f"job {job.id} was submitted without \"color\": \"{color}\"; submit it with "
                "that field to get this colour", errors=[{"field": "color", "index": None,
                                                          "reason": "not computed"}])
    body = await anyio.to_thread.run_sync(_encode, result, fmt, values)
    return Response(body, media_type=MEDIA_TYPES[fmt])


def _encode(result: dict[str, Any], fmt: str, values: Any) -> bytes:
    if fmt == "json":
        return result["body"] if values is None else with_colors(result["body"],
                                                                 colors_for(values))
    mesh = result.get("mesh")
    if mesh is None:
        raise ProblemError("not-acceptable", "this result is not a single mesh; use "
                           "Accept: application/json")
    return mesh_bytes(fmt, mesh["vertices"], mesh["faces"], values)


@router.delete("/v1/jobs/{job_id}", response_model=JobStatus, summary="Cancel or delete a job",
               operation_id="delete_job",
               description="Cancels a queued or running job (200, status `cancelled`; a "
                           "running solve is stopped by replacing its worker). A finished "
                           "job is deleted with its result (204).",
               response_class=Response,
               responses={204: {"description": "Deleted."}, **error_responses(404, 422)})
async def delete_job(request: Request, job_id: JobId) -> Response:
    manager = request.app.state.jobs
    job = await _get(request, job_id)
    if job.done:
        await manager.delete(job)
        return Response(status_code=204)
    await manager.cancel(job)
    return _status_response(job)
