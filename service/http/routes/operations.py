"""The synchronous operations, one route per entry of :data:`service.operations.OPERATIONS`.

Each takes a JSON body, a binary body or a multipart mesh upload, runs in a worker and
answers in the negotiated format (JSON, GLB or glTF for mesh results).
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Awaitable, Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request
from starlette.responses import Response

from service.api.problems import ProblemError, element_error
from service.api.task import Output
from service.http.dependencies import ServicesDep
from service.http.negotiation import JSON_ONLY, MESH_FORMATS, negotiate
from service.http.openapi import GLTF_CONTENT, error_responses, operation_body
from service.http.payloads import operation_request
from service.http.routes import API_PREFIX
from service.http.running import result_response, run_task
from service.operations import OPERATIONS, OperationSpec
from service.worker.output import MEDIA_TYPES

router = APIRouter(prefix=API_PREFIX, tags=["operations"])

COLOR_MEANING = {"defect": "the integrability defect of each vertex",
                 "distortion": "the distortion of the forms at each vertex"}
"""What each vertex colour field shows (``?color=``)."""


def check_color(spec: OperationSpec, color: str | None) -> None:
    """Check that an operation can produce a colour field.

    Args:
        spec: The operation.
        color: The ``?color=`` asked for, or None.

    Raises:
        ProblemError: 422 ``unsupported-color`` when it cannot.
    """
    if color is not None and color not in spec.colors:
        raise ProblemError(
            "unsupported-color",
            f"{spec.name} cannot colour by {color!r}"
            + (f"; it offers {', '.join(spec.colors)}" if spec.colors
               else "; it offers no colours"),
            errors=[element_error("color", f"not offered by {spec.name}")])


def formats(spec: OperationSpec) -> tuple[str, ...]:
    """The result formats of an operation.

    Args:
        spec: The operation.

    Returns:
        The formats its result can be negotiated to, the default first.
    """
    return MESH_FORMATS if spec.mesh_result else JSON_ONLY


def choice_query(values: tuple[str, ...], description: str, **query: Any) -> Any:
    """An optional query parameter that takes one of some values.

    Args:
        values: The values it takes.
        description: Its description in the OpenAPI document.
        **query: More of :func:`fastapi.Query`'s arguments (``alias``).

    Returns:
        The parameter's annotated type.
    """
    return Annotated[Literal[values] | None,  # type: ignore[valid-type]
                     Query(description=description, **query)]


def color_query(colors: tuple[str, ...]) -> Any:
    """The ``?color=`` parameter of an operation offering ``colors``."""
    meaning = "; ".join(f"`{c}`: {COLOR_MEANING[c]}" for c in colors)
    return choice_query(colors, f"Add a per-vertex colour ramp ({meaning}). glTF gets "
                                "COLOR_0, JSON a `colors` array.")


FORMAT_MEANING = {"json": "`application/json`", "glb": "`model/gltf-binary`",
                  "gltf": "`model/gltf+json`",
                  "f32": "`application/octet-stream`, little-endian float32 (n, 3)"}


def format_query(offered: tuple[str, ...]) -> Any:
    """The ``?format=`` parameter offering ``offered``, which overrides ``Accept``."""
    meaning = ", ".join(f"`{f}`: {FORMAT_MEANING[f]}" for f in offered)
    return choice_query(offered, f"The result format ({meaning}); overrides `Accept` (for "
                                 "clients that cannot set it).", alias="format")


def result_format(request: Request, offered: tuple[str, ...], requested: str | None) -> str:
    """The format to answer a request with.

    Args:
        request: The request (its Accept header).
        offered: The formats the endpoint produces.
        requested: Its ``?format=``, or None.

    Returns:
        ``requested`` when given, else the format Accept negotiates.

    Raises:
        ProblemError: 406 ``not-acceptable`` for a format not offered.
    """
    if requested is None:
        return negotiate(request.headers.get("accept"), offered)
    if requested not in offered:
        raise ProblemError("not-acceptable", f"format={requested!r} is not available here; "
                           f"use one of {', '.join(offered)}",
                           available=[MEDIA_TYPES[f] for f in offered])
    return requested


QUERY_PARAMETERS = ("format", "color")
"""The query parameters of an operation's endpoint (each refused where it does nothing)."""


def check_query(request: Request) -> None:
    """Refuse a query parameter the operations do not take, so that a typo (``?colour=``,
    ``?fromat=glb``) is not answered as if it had not been sent.

    Raises:
        ProblemError: 422 ``validation-error`` naming each unknown parameter and its value.
    """
    unknown = [(name, value) for name, value in request.query_params.multi_items()
               if name not in QUERY_PARAMETERS]
    if unknown:
        takes = " and ".join(f"`{name}`" for name in QUERY_PARAMETERS)
        raise ProblemError(
            "validation-error", f"query.{unknown[0][0]}: unknown query parameter (sent: "
            f"{json.dumps(unknown[0][1])}); the operations take {takes}",
            errors=[element_error(f"query.{name}", "unknown query parameter", value=value,
                                  pointer=f"/query/{name}", type="extra_forbidden")
                    for name, value in unknown])


def _endpoint(spec: OperationSpec) -> Callable[..., Awaitable[Response]]:
    """The route function; ``?color=`` and ``?format=`` are documented parameters only where
    they do something (elsewhere a ``color`` is refused with 422 unsupported-color, a
    ``format`` other than ``json`` with 406)."""

    async def endpoint(request: Request, services: ServicesDep, **query: Any) -> Response:
        check_query(request)
        fmt = result_format(request, formats(spec),
                            query.get("fmt", request.query_params.get("format")))
        color = query.get("color", request.query_params.get("color"))
        check_color(spec, color)
        settings = services.settings_for(request)  # a key's face quota
        task = await operation_request(request, spec, settings, Output(fmt, color))
        return result_response(await run_task(request, task, services.backend.executor,
                                              services.metrics, settings.request_timeout))

    parameters = [inspect.Parameter("request", inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                    annotation=Request),
                  inspect.Parameter("services", inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                    annotation=ServicesDep)]
    if spec.mesh_result:
        parameters.append(inspect.Parameter("fmt", inspect.Parameter.KEYWORD_ONLY,
                                            default=None, annotation=format_query(formats(spec))))
    if spec.colors:
        parameters.append(inspect.Parameter("color", inspect.Parameter.KEYWORD_ONLY,
                                            default=None, annotation=color_query(spec.colors)))
    endpoint.__signature__ = inspect.Signature(parameters)  # type: ignore[attr-defined]
    endpoint.__name__ = f"{spec.name.replace('/', '_')}_endpoint"
    return endpoint


for _spec in OPERATIONS.values():
    router.add_api_route(
        f"/{_spec.name}", _endpoint(_spec), methods=["POST"], summary=_spec.summary,
        description=_spec.description, operation_id=_spec.name.replace("/", "_"),
        response_class=Response,
        responses={200: {"model": _spec.response, "description": "The result.",
                         "content": dict(GLTF_CONTENT) if _spec.mesh_result else {}},
                   **error_responses(400, 406, 408, 413, 415, 422, 500, 503, 504)},
        openapi_extra=operation_body(_spec))
