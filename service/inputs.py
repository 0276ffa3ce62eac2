"""Request bodies -> task payloads: size limits, JSON or multipart, schema validation.

Bodies are read here (not by FastAPI) so that one endpoint takes ``application/json``,
``multipart/form-data`` (a mesh file in ``file``, every other field as a JSON-encoded form
value) and ``application/vnd.ffs.arrays`` (the large arrays as raw bytes), and so that the
body limit and the body timeout are enforced while streaming. A synchronous JSON or binary
body is parsed and validated in the worker (:func:`expand_body`); jobs and sessions validate
here, in a thread for large bodies. Arrays are converted to numpy once.
"""

from __future__ import annotations

import asyncio
import gc
from typing import Any

import anyio
import numpy as np
import orjson
from pydantic import BaseModel, ValidationError
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import Request

from service.problems import ProblemError, from_validation_errors
from service.schemas import PARAMS_MODELS
from service.settings import Settings
from service.tasks import check_limits, release_memory
from service.validation import BINARY_MEDIA_TYPE, binary_request, parse_json, request_arrays

FILE_FIELDS: dict[str, tuple[str, ...]] = {"interpolate": ("file_a", "file_b")}
"""Upload field names per operation (default ``("file",)``)."""
FILE_TYPES = ("obj", "ply", "off", "stl", "glb", "gltf")
THREAD_THRESHOLD = 256 * 1024
"""Bodies larger than this are validated in a worker thread, off the event loop."""


def file_fields(operation: str) -> tuple[str, ...]:
    return FILE_FIELDS.get(operation, ("file",))


def media_type(request: Request) -> str:
    """The request's media type without parameters (``application/json`` if absent)."""
    value = request.headers.get("content-type", "")
    return value.split(";", 1)[0].strip().lower() or "application/json"


def is_json(mtype: str) -> bool:
    return mtype == "application/json" or mtype.endswith("+json")


async def read_body(request: Request, settings: Settings) -> bytes:
    """The whole body: a 413 problem as soon as it exceeds FFS_MAX_BODY_BYTES, a 408 (and the
    connection closed) when it takes longer than FFS_BODY_TIMEOUT to arrive. A client that
    disconnects mid-body raises :class:`starlette.requests.ClientDisconnect` (answered 499 and
    logged without a traceback by the app's handler)."""
    limit = settings.max_body_bytes
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise _too_large(int(declared), limit)
    chunks, size = [], 0
    try:
        async with asyncio.timeout(settings.body_timeout):
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise _too_large(size, limit)
                chunks.append(chunk)
    except TimeoutError:
        raise ProblemError(
            "body-timeout", f"the body did not arrive within {settings.body_timeout:g} s "
            f"(FFS_BODY_TIMEOUT; {size} bytes received)", headers={"Connection": "close"},
            errors=[{"field": "body", "index": None,
                     "reason": f"{size} bytes in {settings.body_timeout:g} s"}]) from None
    return b"".join(chunks)


def _too_large(size: int, limit: int) -> ProblemError:
    return ProblemError("payload-too-large",
                        f"the body has at least {size} bytes; the limit is {limit} "
                        "(FFS_MAX_BODY_BYTES)",
                        errors=[{"field": "body", "index": None,
                                 "reason": f"more than {limit} bytes"}])


def validate_object(model: type[BaseModel], data: Any, prefix: tuple[Any, ...] = ()) -> Any:
    """Validate already-parsed data; errors point below ``prefix``."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise from_validation_errors(exc.errors(include_url=False, include_input=False),
                                     prefix) from None


# ------------------------------------------------------------------------------ payloads


def _limits(settings: Settings) -> dict[str, int]:
    return {"max_vertices": settings.max_vertices, "max_faces": settings.max_faces}


def json_source(operation: str, arrays: dict[str, np.ndarray], limits: dict[str, int]
                ) -> dict[str, Any]:
    """The task ``source`` of validated JSON arrays, after the vertex and face limits (413)."""
    if operation in ("integrability", "reconstruct"):
        faces = arrays["faces"]
        n_vertices = int(faces.max()) + 1 if faces.size else 0
        _limit_problem(check_limits, n_vertices, len(faces), limits, "faces")
        return {"kind": "forms", **arrays}
    if operation == "interpolate":
        n_vertices = max(len(arrays["vertices_a"]), len(arrays["vertices_b"]))
        _limit_problem(check_limits, n_vertices, len(arrays["faces"]), limits, "vertices_a")
        return {"kind": "pair", **arrays}
    _limit_problem(check_limits, len(arrays["vertices"]), len(arrays["faces"]), limits,
                   "vertices")
    return {"kind": "arrays", **arrays}


def json_payload(operation: str, doc: Any, limits: dict[str, int], backend: str,
                 prefix: tuple[Any, ...] = ()) -> dict[str, Any]:
    """Task payload of a parsed JSON body (a synchronous body, or a job's ``input``)."""
    arrays, params = request_arrays(operation, doc, prefix)
    return {"source": json_source(operation, arrays, limits), "params": params.model_dump(),
            "limits": limits, "backend": backend}


def expand_body(operation: str, payload: dict[str, Any]) -> dict[str, Any]:
    """A payload whose source is a raw body (``{"kind": "json" | "binary", "body"}``), parsed
    and validated: run in the worker, so that the main process never holds the parsed body."""
    source, limits = payload["source"], payload["limits"]
    if source["kind"] == "binary":
        arrays, params = binary_request(operation, source["body"])
        return {**payload, "source": json_source(operation, arrays, limits),
                "params": params.model_dump()}
    doc = parse_json(source["body"])
    return {**payload, **json_payload(operation, doc, limits, payload["backend"])}


def _limit_problem(fn: Any, *args: Any) -> None:
    from service.tasks import TaskProblemError

    try:
        fn(*args)
    except TaskProblemError as exc:
        raise ProblemError(exc.kind, exc.detail, status=exc.status, errors=exc.errors) from None


async def read_form(request: Request, settings: Settings) -> tuple[dict[str, Any],
                                                                   dict[str, UploadFile]]:
    """Parse a multipart body: (JSON-decoded fields, uploaded files)."""
    body = await read_body(request, settings)
    sent = False

    async def receive() -> dict[str, Any]:
        nonlocal sent
        if sent:
            return {"type": "http.disconnect"}
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    replay = Request(request.scope, receive)
    try:
        form = await replay.form(max_files=4, max_fields=64,
                                 max_part_size=settings.max_body_bytes)
    except StarletteHTTPException as exc:
        raise ProblemError("malformed-request", f"cannot read the multipart body: {exc.detail}"
                           ) from None
    except Exception as exc:  # python-multipart parse errors
        raise ProblemError("malformed-request", f"cannot read the multipart body: {exc}"
                           ) from None
    fields: dict[str, Any] = {}
    files: dict[str, UploadFile] = {}
    for key, value in form.multi_items():
        if isinstance(value, UploadFile):
            files[key] = value
        elif key in fields:
            raise ProblemError("malformed-request", f"form field {key!r} is given twice",
                               errors=[{"field": key, "index": None, "reason": "repeated"}])
        else:
            fields[key] = _decode_field(value)
    return fields, files


def _decode_field(value: str) -> Any:
    """Form values are JSON (``{"a": 1}``, ``[1, 2]``, ``0.5``, ``true``) or plain strings."""
    try:
        return orjson.loads(value)
    except orjson.JSONDecodeError:
        return value


async def upload(file: UploadFile, field: str) -> dict[str, Any]:
    """Read one uploaded mesh file; 415 for an unknown type, 400 for an empty file."""
    from solver.io import UnsupportedFormatError, resolve_format

    name = file.filename or ""
    try:
        resolve_format(name if "." in name else (file.content_type or name))
    except UnsupportedFormatError as exc:
        raise ProblemError(
            "unsupported-file-type",
            f"{field}: {name or file.content_type!r} is not a supported mesh file; upload "
            f"one of {', '.join(FILE_TYPES)}",
            errors=[{"field": field, "index": None, "reason": exc.reason}]) from None
    data = await file.read()
    if not data:
        raise ProblemError("unreadable-file", f"{field}: the file is empty",
                           errors=[{"field": field, "index": None, "reason": "empty file"}])
    return {"kind": "file", "data": data,
            "filename": name if "." in name else (file.content_type or name)}


async def payload_from_form(operation: str, fields: dict[str, Any],
                            files: dict[str, UploadFile], settings: Settings,
                            ) -> dict[str, Any]:
    """Task payload for a multipart upload (mesh file(s) + JSON-encoded form fields)."""
    names = file_fields(operation)
    missing = [n for n in names if n not in files]
    unexpected = [n for n in files if n not in names]
    if missing or unexpected:
        errors = [{"field": n, "index": None, "reason": "a mesh file is required"}
                  for n in missing]
        errors += [{"field": n, "index": None, "reason": f"unexpected file (use {names})"}
                   for n in unexpected]
        raise ProblemError("validation-error", errors[0]["field"] + ": " + errors[0]["reason"],
                           errors=errors)
    params = validate_object(PARAMS_MODELS[operation], fields)
    uploads = {n: await upload(files[n], n) for n in names}
    if operation == "interpolate":
        source: dict[str, Any] = {"kind": "files", "a": uploads["file_a"],
                                  "b": uploads["file_b"]}
    else:
        source = uploads["file"]
    return {"source": source, "params": params.model_dump(), "limits": _limits(settings),
            "backend": settings.solver_backend}


async def parse_operation(request: Request, operation: str, settings: Settings,
                          ) -> dict[str, Any]:
    """Task payload of a synchronous operation request (JSON or multipart).

    A JSON or binary (:data:`service.validation.BINARY_MEDIA_TYPE`) body goes to the worker
    as bytes and is parsed and validated there (:func:`expand_body`), off the event loop and
    out of this process.
    """
    mtype = media_type(request)
    if mtype == "multipart/form-data":
        fields, files = await read_form(request, settings)
        return await payload_from_form(operation, fields, files, settings)
    if is_json(mtype) or mtype == BINARY_MEDIA_TYPE:
        body = await read_body(request, settings)
        kind = "binary" if mtype == BINARY_MEDIA_TYPE else "json"
        return {"source": {"kind": kind, "body": body}, "params": None,
                "limits": _limits(settings), "backend": settings.solver_backend}
    raise unsupported_media_type(mtype)


async def off_loop(size: int, fn: Any, *args: Any) -> Any:
    """Run ``fn(*args)`` in a thread when the input is large (> THREAD_THRESHOLD bytes), then
    give the memory of the parse back to the system before answering."""
    if size <= THREAD_THRESHOLD:
        return fn(*args)
    result, error = await anyio.to_thread.run_sync(_capture, fn, *args)
    gc.collect()
    release_memory()
    if error is not None:
        raise error
    return result


def _capture(fn: Any, *args: Any) -> tuple[Any, BaseException | None]:
    """``(fn(*args), None)`` or ``(None, error)`` with the error's traceback and context
    dropped: their frames hold the parsed body, which must be freed before trimming."""
    try:
        return fn(*args), None
    except Exception as exc:
        exc.__traceback__ = exc.__context__ = exc.__cause__ = None
        return None, exc


def unsupported_media_type(mtype: str) -> ProblemError:
    return ProblemError("unsupported-media-type",
                        f"Content-Type {mtype!r} is not supported; send application/json, "
                        f"multipart/form-data with the mesh in `file`, or {BINARY_MEDIA_TYPE}",
                        errors=[{"field": "Content-Type", "index": None, "reason": mtype}])
