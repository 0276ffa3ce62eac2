"""The synchronous operations, one route per entry of :data:`service.operations.OPERATIONS`.

Each takes a JSON body, a binary body or a multipart mesh upload, runs in a worker and
answers in the negotiated format (JSON, GLB or glTF for mesh results).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request
from starlette.responses import Response

from service.api.problems import ProblemError
from service.api.task import Output
from service.http.dependencies import ServicesDep
from service.http.negotiation import JSON_ONLY, MESH_FORMATS, negotiate
from service.http.openapi import GLTF_CONTENT, error_responses, operation_body
from service.http.payloads import operation_request
from service.http.running import result_response, run_task
from service.operations import OPERATIONS, OperationSpec

router = APIRouter(tags=["operations"])

COLOR_MEANING = {"defect": "the integrability defect of each vertex",
                 "distortion": "the distortion of the forms at each vertex"}
"""What each vertex colour field shows (``?color=``)."""


def check_color(spec: OperationSpec, color: str | None) -> None:
    """422 unless the operation can produce the colour field ``color``."""
    if color is not None and color not in spec.colors:
        raise ProblemError(
            "unsupported-color",
            f"{spec.name} cannot colour by {color!r}"
            + (f"; it offers {', '.join(spec.colors)}" if spec.colors
               else "; it offers no colours"),
            errors=[{"field": "color", "index": None, "reason": f"not offered by {spec.name}"}])


def formats(spec: OperationSpec) -> tuple[str, ...]:
    """The result formats an operation can be negotiated to."""
    return MESH_FORMATS if spec.mesh_result else JSON_ONLY


def color_query(colors: tuple[str, ...]) -> Any:
    """The ``?color=`` parameter offering ``colors``."""
    meaning = "; ".join(f"`{c}`: {COLOR_MEANING[c]}" for c in colors)
    return Annotated[Literal[colors] | None, Query(  # type: ignore[valid-type]
        description=f"Add a per-vertex colour ramp ({meaning}). glTF gets COLOR_0, JSON a "
                    "`colors` array.")]


def _endpoint(spec: OperationSpec) -> Callable[..., Awaitable[Response]]:
    """The route function; ``?color=`` is a documented parameter only where it works (an
    undocumented ``color`` elsewhere is still refused with 422 unsupported-color)."""

    async def run(request: Request, services: ServicesDep, color: str | None) -> Response:
        fmt = negotiate(request.headers.get("accept"), formats(spec))
        check_color(spec, color)
        settings = services.settings
        task = await operation_request(request, spec, settings, Output(fmt, color))
        return result_response(await run_task(request, task, services.backend.executor,
                                              services.metrics, settings.request_timeout))

    if spec.colors:
        async def endpoint(request: Request, services: ServicesDep,
                           color: Any = None) -> Response:
            return await run(request, services, color)

        endpoint.__annotations__["color"] = color_query(spec.colors)
    else:
        async def endpoint(request: Request, services: ServicesDep) -> Response:
            return await run(request, services, request.query_params.get("color"))

    endpoint.__name__ = f"{spec.name}_endpoint"
    return endpoint


for _spec in OPERATIONS.values():
    router.add_api_route(
        f"/v1/{_spec.name}", _endpoint(_spec), methods=["POST"], summary=_spec.summary,
        description=_spec.description, operation_id=_spec.name, response_class=Response,
        responses={200: {"model": _spec.response, "description": "The result.",
                         "content": dict(GLTF_CONTENT) if _spec.mesh_result else {}},
                   **error_responses(400, 406, 408, 413, 415, 422, 500, 503, 504)},
        openapi_extra=operation_body(_spec))
