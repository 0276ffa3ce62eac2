"""Liveness, readiness, Prometheus metrics and the problem-type catalogue."""

from __future__ import annotations

from fastapi import APIRouter
from starlette.responses import PlainTextResponse, Response

from service.api.documents import Health, ProblemKind, Readiness
from service.api.problems import PROBLEM_KINDS, ProblemError, problem_type
from service.http.dependencies import MetricsDep, ServicesDep
from service.http.metrics import METRICS_CONTENT_TYPE
from service.http.routes import model_response
from service.worker.output import json_bytes

router = APIRouter(tags=["health"])


@router.get("/healthz", operation_id="healthz", response_model=Health, summary="Liveness",
            description="200 while the process serves HTTP.")
async def healthz() -> Response:
    return model_response(Health(status="ok"))


@router.get("/readyz", operation_id="readyz", response_model=Readiness, summary="Readiness",
            description="200 when the worker pool can take work, else 503 (same body).",
            responses={503: {"model": Readiness, "description": "The pool is not ready."}})
async def readyz(services: ServicesDep) -> Response:
    executor = services.backend.executor
    ready = executor.ready()
    doc = Readiness(
        status="ready" if ready else ("starting" if services.started else "unavailable"),
        workers=executor.size(), workers_ready=executor.workers_ready(), busy=executor.busy(),
        queue_depth=executor.queue_depth())
    return model_response(doc, 200 if ready else 503)


@router.get("/metrics", operation_id="metrics", summary="Prometheus metrics",
            description="Request counts and latencies per route, solver stage timings, queue "
                        "depth, pool size (Prometheus text format).",
            response_class=PlainTextResponse,
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                             "description": "Prometheus exposition format."}})
async def metrics(registry: MetricsDep) -> Response:
    return Response(registry.render(), media_type=METRICS_CONTENT_TYPE)


def _kind(kind: str) -> ProblemKind:
    status, title, description = PROBLEM_KINDS[kind]
    return ProblemKind(type=problem_type(kind), kind=kind, status=status, title=title,
                       description=description)


@router.get("/problems", operation_id="list_problems", response_model=list[ProblemKind],
            summary="Problem types",
            description="Every problem `type` this service returns.")
async def problems() -> Response:
    return Response(json_bytes([_kind(kind).model_dump() for kind in sorted(PROBLEM_KINDS)]),
                    media_type="application/json")


@router.get("/problems/{kind}", operation_id="get_problem", response_model=ProblemKind,
            summary="One problem type",
            responses={404: {"description": "Unknown problem type."}})
async def problem(kind: str) -> Response:
    if kind not in PROBLEM_KINDS:
        raise ProblemError("not-found", f"no problem type {kind!r}")
    return model_response(_kind(kind))
