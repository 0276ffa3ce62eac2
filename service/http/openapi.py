"""The OpenAPI document: request bodies that FastAPI cannot infer (JSON *or* multipart),
problem responses as ``application/problem+json``, and every schema with an example.

``scripts/generate_openapi.py`` writes it to ``openapi/openapi.json``; a test fails when that
file is stale.
"""

from __future__ import annotations

import copy
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic import BaseModel
from pydantic.json_schema import models_json_schema

from service.api.decoding import BINARY_DTYPES, BINARY_MEDIA_TYPE, MAX_SHAPES
from service.api.documents import Problem
from service.api.schemas import JobRequest, SessionDrag, SessionRequest
from service.http.problems import PROBLEM_MEDIA_TYPE
from service.operations import OPERATIONS, OperationSpec

REF = "#/components/schemas/{model}"
ERROR_DESCRIPTIONS: dict[int, str] = {
    400: "Malformed JSON, multipart body or mesh file.",
    404: "Unknown job or session (or it expired).",
    408: "The body did not arrive within FFS_BODY_TIMEOUT seconds.",
    406: "None of the Accept media types can be produced.",
    409: "The job has no result (not finished, failed or cancelled).",
    410: "The session expired or its worker died; or the job was submitted before the "
         "service restarted (`job-lost`).",
    413: "Body, vertex or face count over the limit.",
    415: "Unsupported Content-Type or mesh file type.",
    429: "Too many open sessions (FFS_MAX_SESSIONS), or this client's unfinished jobs "
         "(FFS_MAX_CLIENT_JOBS).",
    422: "Schema violation, or a solver input error (one problem kind per error class).",
    500: "A worker process died.",
    503: "Queue full (Retry-After), the pool is not running, or session memory is "
         "exhausted.",
    504: "No result within FFS_REQUEST_TIMEOUT.",
}


GLTF_CONTENT = {
    "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}},
    "model/gltf+json": {"schema": {"type": "object",
                                   "description": "glTF 2.0 with the buffer as a data URI."}},
}
"""The glTF media types of a mesh result."""


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The ``responses=`` entries of problem documents.

    Args:
        *codes: The HTTP statuses an operation may answer with a problem.

    Returns:
        An entry per status, its description (its content is filled in by :func:`build`).
    """
    return {code: {"description": ERROR_DESCRIPTIONS[code]} for code in codes}


def created(description: str, location: str, parameter: str,
            targets: dict[str, str]) -> dict[str, Any]:
    """A 201/202 response that creates a resource.

    Args:
        description: The response's description.
        location: The ``Location`` header's form (``/v1/jobs/{id}``).
        parameter: The path parameter the created ``id`` fills (``job_id``).
        targets: Link names to the operation ids on the resource.

    Returns:
        The response: its ``Location`` header and OpenAPI ``links`` from the created
        resource's ``id`` to the operations on it (clients and stateful fuzzers follow them).
    """
    return {"description": description,
            "headers": {"Location": {"schema": {"type": "string"}, "description": location}},
            "links": {name: {"operationId": operation,
                             "parameters": {parameter: "$response.body#/id"}}
                      for name, operation in targets.items()}}


def _example(model: type[BaseModel]) -> Any:
    extra = model.model_config.get("json_schema_extra") or {}
    examples = extra.get("examples") if isinstance(extra, dict) else None
    return copy.deepcopy(examples[0]) if examples else None


FILE_DESCRIPTION = ("Mesh file: OBJ, PLY, OFF, STL or GLB (vertex order and faces are kept as "
                    "in the file).")
SCALAR_TYPES = frozenset({"number", "integer", "boolean", "string"})


def form_field(schema: dict[str, Any], description: str | None) -> dict[str, Any]:
    """A parameter field as a multipart property.

    Args:
        schema: The field's JSON schema.
        description: Its description, if any.

    Returns:
        The property: ``null`` left out (omit the field instead), and how to send it
        (arrays: one part per item, or the whole array as one JSON part).
    """
    schema = dict(schema)
    members = [m for m in schema.pop("anyOf", []) if m.get("type") != "null"]
    if len(members) == 1:
        schema.update(members[0])
    elif members:
        schema["anyOf"] = members
    if schema.get("default", 0) is None:
        del schema["default"]
    shapes = [schema, *members]
    if any(m.get("type") == "array" and m.get("items", {}).get("type") == "array"
           for m in shapes):  # no multipart form of nested arrays: the whole array as JSON
        return {"type": "string", "contentMediaType": "application/json",
                "contentSchema": {k: v for k, v in schema.items() if k != "title"},
                "description": "The whole array as one JSON part such as `[[1, 2, 3]]`"
                               + (f". {description}" if description else ".")}
    if any(m.get("type") == "array" for m in shapes):
        how = ("One part per item (each a JSON value), or the whole array as one JSON part "
               "such as `[1, 2]`")
    elif _is_scalar(schema):
        how = "A form value such as `0.5` or `true`"
    else:
        how = "A JSON part such as `{\"a\": 1}`"
    schema["description"] = how + (f". {description}" if description else ".")
    return schema


def _is_scalar(schema: dict[str, Any]) -> bool:
    return schema.get("type") in SCALAR_TYPES or any(
        m.get("type") in SCALAR_TYPES for m in schema.get("anyOf", []))


def form_properties(spec: OperationSpec) -> dict[str, Any]:
    """The multipart properties of an operation's parameter fields.

    Args:
        spec: The operation.

    Returns:
        The properties (parsed as JSON where they are JSON; see :func:`form_encoding`).
    """
    field_schemas = params_schema(spec.params)["properties"]
    return {name: form_field(field_schemas[name], info.description)
            for name, info in spec.params.model_fields.items()}


def file_schema(spec: OperationSpec) -> dict[str, Any]:
    """The schema of an operation's upload field: one binary part, or (``file_list``) one
    part per mesh, in order."""
    one = {"type": "string", "format": "binary", "description": FILE_DESCRIPTION}
    if not spec.file_list:
        return one
    return {"type": "array", "items": {"type": "string", "format": "binary"},
            "minItems": 1, "maxItems": MAX_SHAPES,
            "description": FILE_DESCRIPTION + " One part per mesh, in order (the same "
                           "faces in each)."}


def multipart_schema(spec: OperationSpec) -> dict[str, Any]:
    """The schema of an operation's multipart form.

    Args:
        spec: The operation.

    Returns:
        The mesh file(s) plus the parameter fields, each with its real schema.
    """
    params = spec.params
    properties: dict[str, Any] = {name: file_schema(spec) for name in spec.files}
    properties.update(form_properties(spec))
    required = [*spec.files, *(n for n, f in params.model_fields.items() if f.is_required())]
    example: dict[str, Any] = {name: ([f"<{name}-0.off>", f"<{name}-1.off>"] if spec.file_list
                                      else f"<{name}.off>") for name in spec.files}
    example.update(_example(params) or {})  # the values themselves
    return {"type": "object", "properties": properties, "required": required,
            "additionalProperties": False, "examples": [example]}


def params_schema(model: type[BaseModel]) -> dict[str, Any]:
    """The JSON schema of a params model.

    Args:
        model: The model.

    Returns:
        Its schema, with references into ``components/schemas``.
    """
    _, defs = models_json_schema([(model, "validation")], ref_template=REF)
    return defs["$defs"][model.__name__]


def form_encoding(properties: dict[str, Any]) -> dict[str, Any]:
    """The multipart ``encoding`` of form properties.

    Args:
        properties: The form's properties.

    Returns:
        An entry per field that is not a scalar: sent as JSON (for an array: each part).
    """
    return {name: {"contentType": "application/json"} for name, schema in properties.items()
            if schema.get("format") != "binary"
            and (schema.get("items") or {}).get("format") != "binary"
            and (not _is_scalar(schema) or "contentSchema" in schema)}


def operation_body(spec: OperationSpec) -> dict[str, Any]:
    """The ``openapi_extra`` of a synchronous operation.

    Args:
        spec: The operation.

    Returns:
        Its request body: JSON, a multipart upload, or the binary arrays.
    """
    model = spec.request
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": REF.format(model=model.__name__)},
                             "example": _example(model)},
        "multipart/form-data": {"schema": (form := multipart_schema(spec)),
                                "encoding": form_encoding(form["properties"])},
        BINARY_MEDIA_TYPE: {"schema": {
            "type": "string", "format": "binary",
            "description": binary_description(spec),
            "examples": ["FFSA <uint32 header length> <JSON header> <padding> <arrays>"]}},
    }}}


def binary_description(spec: OperationSpec) -> str:
    """What a binary body of an operation holds (the format: docs/service.md).

    Args:
        spec: The operation.

    Returns:
        The description: its arrays with their shapes and dtypes.
    """
    names = ", ".join(f"`{n}` ({f'(n, {s.cols})' if s.cols else '(n,)'} "
                      f"{'indices' if s.integer else 'reals'})"
                      for n, s in spec.arrays.items())
    return ("The JSON body with its large arrays as raw little-endian bytes: `FFSA`, a uint32 "
            "header length, a JSON header (the other fields of the JSON body plus "
            "`\"arrays\": {name: {\"dtype\", \"shape\"}}` in the order they follow), zero "
            "padding to a multiple of 8, then each array (C order) padded to a multiple of 8. "
            f"dtypes: {', '.join(f'`{d}`' for d in BINARY_DTYPES)}. Arrays: {names}.")


def job_form_properties() -> dict[str, Any]:
    """The parameter fields of every operation, for a job upload: a field that two
    operations type differently (``options``) is either type."""
    merged: dict[str, list[dict[str, Any]]] = {}
    for spec in OPERATIONS.values():
        for name, schema in form_properties(spec).items():
            schema.pop("default", None)  # the operation's default, not the job's
            variants = merged.setdefault(name, [])
            if schema not in variants:
                variants.append(schema)
    properties = {}
    for name, variants in merged.items():
        if len(variants) == 1:
            properties[name] = variants[0]
        else:
            properties[name] = {"anyOf": [{k: v for k, v in variant.items()
                                           if k not in ("description", "title")}
                                          for variant in variants],
                                "description": variants[0]["description"].split(". ")[0]
                                + ", of the type the job's `operation` takes."}
    return properties


def jobs_body() -> dict[str, Any]:
    """The ``openapi_extra`` of ``POST /v1/jobs``.

    Returns:
        Its request body: JSON (``JobRequest``) or a multipart upload of any operation.
    """
    properties: dict[str, Any] = {
        "operation": {"type": "string", "enum": list(OPERATIONS)},
        "color": {"type": "string", "enum": ["defect", "distortion"]},
        "callback_url": {"type": "string", "maxLength": 2048,
                         "description": "Where to POST the finished job's status, signed "
                                        "(services with API keys; FFS_WEBHOOK_HOSTS)."},
        "file": {"type": "string", "format": "binary",
                 "description": FILE_DESCRIPTION + " `file_a` and `file_b` for interpolate; "
                 "one `shapes` part per mesh for blend; `file_source`, "
                 "`file_source_deformed` and `file_target` for transfer."},
        "file_a": {"type": "string", "format": "binary"},
        "file_b": {"type": "string", "format": "binary"},
        **{name: {k: v for k, v in file_schema(spec).items() if k != "description"}
           for spec in OPERATIONS.values() for name in spec.files
           if name not in ("file", "file_a", "file_b")},  # blend's shapes, transfer's files
        **job_form_properties(),
    }
    upload = {"type": "object", "required": ["operation"], "properties": properties,
              "additionalProperties": False,
              "description": "The mesh file(s) and the operation's other fields, as in its "
                             "synchronous upload.",
              "examples": [{"operation": "reconstruct", "file": "<face.off>",
                            "options": {"orthonormalize": True}}]}
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": REF.format(model=JobRequest.__name__)},
                             "example": _example(JobRequest)},
        "multipart/form-data": {"schema": upload, "encoding": form_encoding(properties)},
    }}}


EXTRA_MODELS: tuple[type[BaseModel], ...] = (*(s.request for s in OPERATIONS.values()),
                                              JobRequest, Problem, SessionRequest, SessionDrag)
"""Models referenced by hand-written request bodies: every ``$ref`` must resolve."""


def build(app: FastAPI) -> dict[str, Any]:
    """The app's OpenAPI document.

    Args:
        app: The application.

    Returns:
        The document (cached on the app).
    """
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, description=app.description,
                         routes=app.routes, tags=app.openapi_tags)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    _, defs = models_json_schema([(m, "validation") for m in EXTRA_MODELS], ref_template=REF)
    for name, definition in defs.get("$defs", {}).items():
        components.setdefault(name, definition)
    for name in ("HTTPValidationError", "ValidationError"):
        components.pop(name, None)
    problem_ref = {"$ref": REF.format(model="Problem")}
    for path_item in schema.get("paths", {}).values():
        for operation in path_item.values():
            for code, response in operation.get("responses", {}).items():
                if code.isdigit() and int(code) >= 400 and "readyz" not in str(
                        operation.get("operationId")):
                    response["content"] = {PROBLEM_MEDIA_TYPE: {"schema": problem_ref}}
                    if int(code) == 422 and response.get("description") == "Validation Error":
                        response["description"] = ERROR_DESCRIPTIONS[422]
    schema["components"]["schemas"] = dict(sorted(components.items()))
    app.openapi_schema = schema
    return schema
