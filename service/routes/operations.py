"""The synchronous operations: forms, integrability, reconstruct, deform, parameterize,
interpolate, mesh. Each takes a JSON body or a multipart mesh upload, runs in a worker and answers
in the negotiated format (JSON, GLB or glTF for mesh results).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request
from starlette.responses import Response

from service.inputs import file_fields, parse_operation
from service.negotiation import JSON_ONLY, MESH_FORMATS, negotiate
from service.openapi import error_responses, operation_body
from service.problems import ProblemError
from service.runner import result_response, run_task
from service.schemas import (
    ColorField,
    FormsResponse,
    IntegrabilityResponse,
    InterpolateResponse,
    MeshResponse,
    ParameterizeResponse,
)
from service.tasks import COLOR_FIELDS, MESH_OPERATIONS

router = APIRouter(tags=["operations"])

ColorQuery = Annotated[ColorField | None, Query(
    description="Add a per-vertex colour ramp of this field (a job precomputed with `color`): "
                "`defect` (reconstruct: the integrability defect) or `distortion` (deform). "
                "glTF gets COLOR_0, JSON a `colors` array.")]
_COLOR_MEANING = {"defect": "the integrability defect of each vertex",
                  "distortion": "the distortion of the forms at each vertex"}


def _color_query(operation: str) -> Any:
    """The ``?color=`` parameter of an operation that offers colours: only its fields."""
    offered = COLOR_FIELDS[operation]
    meaning = "; ".join(f"`{c}`: {_COLOR_MEANING[c]}" for c in offered)
    return Annotated[Literal[offered] | None, Query(  # type: ignore[valid-type]
        description=f"Add a per-vertex colour ramp ({meaning}). glTF gets COLOR_0, JSON a "
                    "`colors` array.")]


_GLTF_CONTENT = {
    "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}},
    "model/gltf+json": {"schema": {"type": "object",
                                   "description": "glTF 2.0 with the buffer as a data URI."}},
}

SPECS: dict[str, dict[str, Any]] = {
    "forms": {
        "model": FormsResponse, "summary": "Fundamental forms of a mesh",
        "description": "Edge lengths and signed dihedral angles of a mesh. The result is a "
                       "valid body for /v1/integrability and /v1/reconstruct."},
    "integrability": {
        "model": IntegrabilityResponse, "summary": "Integrability report",
        "description": "Checks whether lengths and angles come from a surface: per-vertex "
                       "holonomy defects (Gauss and Codazzi parts), triangle inequality, "
                       "topology and the global holonomy along homology generators. A mesh "
                       "file upload is checked through its own forms."},
    "reconstruct": {
        "model": MeshResponse, "summary": "Reconstruct a mesh from its forms",
        "description": "One sparse linear solve (Eq. 5) with optional position and frame "
                       "constraints. The integrability condition is always checked first and "
                       "summarized in `report.integrability`; with "
                       "`options.require_integrable` a failed check is a 422 naming the "
                       "worst vertices. A mesh file upload is reconstructed from its own "
                       "forms."},
    "deform": {
        "model": MeshResponse, "summary": "Deform a mesh with handles",
        "description": "Moves handle vertices (and optionally rotates groups of face frames) "
                       "while preserving the fundamental forms as well as possible; "
                       "`report.distortion` measures the change."},
    "parameterize": {
        "model": ParameterizeResponse, "summary": "Flatten a mesh with boundary",
        "description": "Planar coordinates by reconstructing with all dihedral angles 0. "
                       "Closed meshes are a 422 (unsupported-topology). glTF output is the "
                       "flat mesh (u, v, 0)."},
    "interpolate": {
        "model": InterpolateResponse, "summary": "Interpolate two meshes in form space",
        "description": "Blends lengths and dihedral angles of two embeddings of the same "
                       "faces and reconstructs for each t. glTF output needs a single t. "
                       "Uploads use `file_a` and `file_b`."},
    "mesh": {
        "model": MeshResponse, "summary": "Read or convert a mesh",
        "description": "Reads a mesh file (OBJ, PLY, OFF, STL, GLB) or a JSON mesh, checks "
                       "its connectivity like the other operations do, and returns it in the "
                       "negotiated format: JSON `vertices` (file order) and `faces` with a "
                       "`report` (counts, bounds, mean edge length), or GLB / glTF. The web "
                       "page uses it to open uploads and to download the current mesh."},
}


def check_color(operation: str, color: str | None) -> None:
    """422 unless ``operation`` can produce the colour field ``color``."""
    if color is not None and color not in COLOR_FIELDS.get(operation, ()):
        offered = COLOR_FIELDS.get(operation, ())
        raise ProblemError(
            "unsupported-color",
            f"{operation} cannot colour by {color!r}"
            + (f"; it offers {', '.join(offered)}" if offered else "; it offers no colours"),
            errors=[{"field": "color", "index": None, "reason": f"not offered by {operation}"}])


def _endpoint(operation: str) -> Callable[..., Awaitable[Response]]:
    """The route function; ``?color=`` is a documented parameter only where it works (an
    undocumented ``color`` elsewhere is still refused with 422 unsupported-color)."""
    formats = MESH_FORMATS if operation in MESH_OPERATIONS else JSON_ONLY

    async def run(request: Request, color: str | None) -> Response:
        fmt = negotiate(request.headers.get("accept"), formats)
        check_color(operation, color)
        payload = await parse_operation(request, operation, request.app.state.settings)
        payload["output"] = {"format": fmt, "color": color, "compute": [], "keep": False}
        return result_response(await run_task(request, operation, payload))

    if operation in COLOR_FIELDS:
        async def endpoint(request: Request, color: Any = None) -> Response:
            return await run(request, color)

        endpoint.__annotations__["color"] = _color_query(operation)
    else:
        async def endpoint(request: Request) -> Response:
            return await run(request, request.query_params.get("color"))

    endpoint.__name__ = f"{operation}_endpoint"
    return endpoint


for _operation, _spec in SPECS.items():
    _content = _GLTF_CONTENT if _operation in MESH_OPERATIONS else {}
    router.add_api_route(
        f"/v1/{_operation}", _endpoint(_operation), methods=["POST"],
        summary=_spec["summary"], description=_spec["description"],
        operation_id=_operation, response_class=Response,
        responses={200: {"model": _spec["model"], "description": "The result.",
                         "content": dict(_content)},
                   **error_responses(400, 406, 408, 413, 415, 422, 500, 503, 504)},
        openapi_extra=operation_body(_operation, file_fields(_operation)))
