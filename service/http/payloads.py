"""What a request body becomes: a :class:`~service.api.task.TaskRequest` (an operation or a
job) or a :class:`~service.api.task.SessionSpec` (a session), built once, here.

* A synchronous JSON or binary body goes to the worker as bytes (a ``RawBody``): the worker
  parses and validates it (:func:`service.api.decoding.decode_raw`), so the event loop and
  the main process's memory never hold the parsed arrays.
* A multipart upload: the form fields are validated here against the operation's params
  model; the files go to the worker, which reads them.
* A JSON job and a session body are parsed here (the job's ``operation`` and the session's
  handles are needed before anything runs), in a thread when they are large and in the
  app's parser process when they are larger still (:func:`service.http.bodies.off_loop`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from starlette.datastructures import UploadFile
from starlette.requests import Request

from service.api.budgets import TIME_POLICY
from service.api.decoding import (
    BINARY_MEDIA_TYPE,
    MAX_SHAPES,
    MESH_ARRAYS,
    check_limits,
    check_work,
    decode_document,
    decode_json,
    parse_json,
)
from service.api.problems import ProblemError, element_error
from service.api.schemas import JobRequest, SessionParams
from service.api.task import (
    Limits,
    Output,
    RawBody,
    SessionSpec,
    TaskRequest,
)
from service.backends.admission import Pricing, pricing, sync_faces_within
from service.http.bodies import (
    ParserPool,
    as_arrays,
    is_json,
    media_type,
    off_loop,
    read_body,
    read_form,
    unsupported_media_type,
    upload,
    validate_object,
)
from service.memory import gc_paused
from service.operations import OPERATIONS, OperationSpec
from service.settings import Settings


def limits(settings: Settings, operation: str | None = None, synchronous: bool = False
           ) -> Limits:
    """The size limits a task carries to its worker: the one place an operation's limits
    are computed (:func:`sync_limits` and ``GET /v1/me``'s :func:`size_limits` read them).

    Args:
        settings: FFS_MAX_VERTICES, FFS_MAX_FACES, FFS_MAX_BLEND_STEPS,
            FFS_MAX_BLEND_VERTICES, FFS_MAX_REQUEST_MEMORY and FFS_REQUEST_TIMEOUT.
        operation: the operation (a key of :data:`service.operations.OPERATIONS`), or None
            for a session (which factorizes).
        synchronous: a synchronous request (then ``max_sync_faces`` too), not a job or a
            session.

    Returns:
        The limits: at most FFS_MAX_FACES faces, and at most the faces whose predicted peak
        memory, by the path the solver takes within FFS_MAX_REQUEST_MEMORY
        (:mod:`service.backends.admission`), fits it; for an operation with an iterative
        path the faces its factorization fits and the limits of its linear answer
        (``Limits.linear``); for a synchronous request the most faces whose first answer is
        predicted within FFS_REQUEST_TIMEOUT less the margin for encoding the answer, by the
        path the solver takes (:meth:`service.backends.admission.Pricing.sync_faces_within`;
        beyond: 413 ``use-a-job``).
    """
    spec = OPERATIONS.get(operation) if operation is not None else None
    solves, iterative = spec is None or spec.solves, spec is not None and spec.iterative
    seconds = None
    if synchronous:
        seconds = settings.request_timeout - TIME_POLICY.encode_margin(settings.request_timeout)
    size = _limits(settings, pricing(solves, iterative), seconds)
    if iterative:
        size = replace(size, linear=_limits(settings, pricing(solves, iterative, linear=True),
                                            seconds))
    return size


def _limits(settings: Settings, how: Pricing, seconds: float | None) -> Limits:
    """The limits of an operation priced ``how`` (synchronous with ``seconds``)."""
    memory = settings.max_request_memory
    fit = how.faces_within(memory)
    direct = (min(how.direct_faces(memory), settings.max_faces)
              if how.iterative is not None else None)
    bound = fit < settings.max_faces
    most = min(fit, settings.max_faces)
    # Never above the size limit, which is checked first: a synchronous limit beyond it would
    # tell a caller (GET /v1/me) of faces no request may bring.
    sync = (min(sync_faces_within(seconds, how, memory), most)
            if seconds is not None else None)
    return Limits(settings.max_vertices, most, settings.max_blend_steps,
                  settings.max_blend_vertices, memory if bound else None,
                  max_sync_faces=sync, sync_seconds=seconds, request_memory=memory,
                  max_direct_faces=direct)


def sync_limits(settings: Settings, operation: str) -> Limits:
    """:func:`limits` of a synchronous request of ``operation``."""
    return limits(settings, operation, synchronous=True)


def size_limits(settings: Settings) -> dict[str, Any]:
    """The size limits ``GET /v1/me`` shows (:class:`service.api.documents.SizeLimits`):
    FFS_MAX_VERTICES, FFS_MAX_FACES, FFS_MAX_BODY_BYTES, FFS_MAX_REQUEST_MEMORY, and each
    operation's limits as a synchronous request takes them (:func:`sync_limits`): its faces
    (and a session's, :func:`limits`), its faces synchronously, and for the operations with
    an iterative path the faces their factorization takes and those their linear answer
    (``options.refine: false``, ``Limits.linear``) takes, in all and synchronously."""
    operations = {name: sync_limits(settings, name) for name in OPERATIONS}
    by_operation = {name: size.max_faces for name, size in operations.items()}
    by_operation["sessions"] = limits(settings).max_faces
    iterative = {name: size for name, size in operations.items()
                 if size.max_direct_faces is not None}
    return {"max_vertices": settings.max_vertices, "max_faces": settings.max_faces,
            "max_body_bytes": settings.max_body_bytes,
            "max_request_memory": settings.max_request_memory,
            "max_faces_by_operation": by_operation,
            "max_sync_faces_by_operation": {name: size.max_sync_faces
                                            for name, size in operations.items()},
            "max_direct_faces_by_operation": {name: size.max_direct_faces
                                              for name, size in iterative.items()},
            "max_linear_faces_by_operation": {name: (size.linear or size).max_faces
                                              for name, size in iterative.items()},
            "max_linear_sync_faces_by_operation": {name: (size.linear or size).max_sync_faces
                                                   for name, size in iterative.items()}}


async def operation_request(request: Request, spec: OperationSpec, settings: Settings,
                            output: Output) -> TaskRequest:
    """The task of a synchronous operation request.

    Args:
        request: The request (JSON, binary or multipart).
        spec: The operation.
        settings: The limits and the solver backend.
        output: The negotiated result format.

    Returns:
        The task (a JSON or binary body goes to the worker unparsed).

    Raises:
        ProblemError: 415 for another media type; the problems of reading the body.
    """
    mtype = media_type(request)
    if mtype == "multipart/form-data":
        fields, files = await read_form(request, settings)
        return await form_request(spec, fields, files, settings, output, synchronous=True)
    if is_json(mtype) or mtype == BINARY_MEDIA_TYPE:
        body = await read_body(request, settings)
        kind = "binary" if mtype == BINARY_MEDIA_TYPE else "json"
        return TaskRequest(spec.name, RawBody(kind, body), limits=sync_limits(settings, spec.name),
                           backend=settings.solver_backend, output=output)
    raise unsupported_media_type(mtype)


async def form_request(spec: OperationSpec, fields: dict[str, Any],
                       files: dict[str, UploadFile | list[UploadFile]], settings: Settings,
                       output: Output, *, synchronous: bool = False) -> TaskRequest:
    """The task of a multipart upload.

    Args:
        spec: The operation.
        fields: The JSON-decoded form fields, validated here against its params.
        files: The uploaded mesh file(s), read by the worker; a list where a field was
            repeated, which only an operation's ``file_list`` field may be (``blend``'s
            ``shapes``: one part per mesh, in order).
        settings: The limits and the solver backend.
        output: The negotiated result format.
        synchronous: A synchronous request (:func:`sync_limits`), not a job.

    Returns:
        The task.

    Raises:
        ProblemError: 422 for a missing or unexpected file or an invalid field, 400
            ``malformed-request`` for a repeated file field that is not a list; the
            problems of :func:`service.http.bodies.upload`.
    """
    missing = [n for n in spec.files if n not in files]
    unexpected = [n for n in files if n not in spec.files]
    if missing or unexpected:
        errors = [element_error(n, "a mesh file is required")
                  for n in missing]
        errors += [element_error(n, f"unexpected file (use {spec.files})")
                   for n in unexpected]
        raise ProblemError("validation-error", errors[0]["field"] + ": " + errors[0]["reason"],
                           errors=errors)
    params = validate_object(spec.params, as_arrays(spec.params, fields))
    check_work(params.model_dump(), limits(settings, spec.name))
    parts: list[tuple[UploadFile, str]] = []
    for name in spec.files:
        given = files[name]
        if isinstance(given, list) and not spec.file_list:
            raise ProblemError("malformed-request", f"form field {name!r} is given twice",
                               errors=[element_error(name, "repeated")])
        if spec.file_list:
            listed = given if isinstance(given, list) else [given]
            if len(listed) > MAX_SHAPES:
                raise ProblemError("validation-error", f"{name}: {len(listed)} files; at most "
                                   f"{MAX_SHAPES} are allowed", errors=[element_error(
                                       name, f"at most {MAX_SHAPES} files", type="too_long")])
            parts += [(file, f"{name}[{k}]") for k, file in enumerate(listed)]
        else:
            parts.append((given, name))
    uploads = [await upload(file, field) for file, field in parts]
    source = tuple(uploads) if spec.file_list or len(uploads) > 1 else uploads[0]
    size = sync_limits(settings, spec.name) if synchronous else limits(settings, spec.name)
    return TaskRequest(spec.name, source, params.model_dump(), size, settings.solver_backend,
                       output)


JOB_MEDIA_TYPES = ('application/json ({"operation", "input"})',
                   "multipart/form-data with an `operation` field and the mesh in `file`")
"""What ``POST /v1/jobs`` takes, in words."""


async def job_request(request: Request, settings: Settings, parser: ParserPool
                      ) -> tuple[str | None, TaskRequest]:
    """(colour, task) of ``POST /v1/jobs`` (:func:`job_submission`)."""
    head, task = await job_submission(request, settings, parser)
    return head.color, task


async def job_submission(request: Request, settings: Settings, parser: ParserPool
                         ) -> tuple[JobRequest, TaskRequest]:
    """(head, task) of ``POST /v1/jobs``: JSON ``{"operation", "input", "color"?,
    "callback_url"?}`` (the input validated like the synchronous body, in ``parser`` when it
    is large) or a multipart upload with ``operation``, ``color`` and ``callback_url``
    fields. The task keeps its mesh arrays and the wanted colour for later."""
    mtype = media_type(request)
    if mtype == "multipart/form-data":
        fields, files = await read_form(request, settings)
        head = validate_object(JobRequest, {  # a missing operation is "Field required"
            **{name: fields.pop(name) for name in ("operation",) if name in fields},
            "color": fields.pop("color", None), "input": {},
            "callback_url": fields.pop("callback_url", None)})
        task = await form_request(OPERATIONS[head.operation], fields, files, settings,
                                  Output())
    elif is_json(mtype):
        body = await read_body(request, settings)
        head, task = await off_loop(parser, len(body), _json_job, body, settings)
    else:
        raise unsupported_media_type(mtype, JOB_MEDIA_TYPES)
    return head, task.with_output(Output(compute=(head.color,) if head.color else (),
                                         keep=True))


def _json_job(body: bytes, settings: Settings) -> tuple[JobRequest, TaskRequest]:
    with gc_paused():
        head = validate_object(JobRequest, parse_json(body))
        source, params = decode_document(OPERATIONS[head.operation], head.input,
                                         limits(settings, head.operation), prefix=("input",))
    return head, TaskRequest(head.operation, source, params, limits(settings, head.operation),
                             settings.solver_backend)


SESSION_MEDIA_TYPES = ("application/json (a session takes no file upload: read the mesh with "
                       "POST /v1/mesh first)",)
"""What ``POST /v1/sessions`` takes, in words."""


async def session_spec(request: Request, settings: Settings, parser: ParserPool
                       ) -> SessionSpec:
    """The spec of ``POST /v1/sessions`` (JSON only; the mesh is validated as arrays, in
    ``parser`` when the body is large)."""
    mtype = media_type(request)
    if not is_json(mtype):
        raise unsupported_media_type(mtype, SESSION_MEDIA_TYPES)
    body = await read_body(request, settings)
    spec: SessionSpec = await off_loop(parser, len(body), _session_spec, body, settings)
    return spec


def _session_spec(body: bytes, settings: Settings) -> SessionSpec:
    with gc_paused():
        arrays, model = decode_json(MESH_ARRAYS, SessionParams, parse_json(body))
    vertices, faces = arrays["vertices"], arrays["faces"]
    size = limits(settings)
    check_limits(len(vertices), len(faces), size, "vertices", "faces")
    assert isinstance(model, SessionParams)
    return SessionSpec(
        vertices, faces, np.array([h.vertex for h in model.handles], dtype=np.int64),
        tuple(np.asarray(r.faces, dtype=np.int64) for r in model.rotations or []),
        None if model.roi is None else np.asarray(model.roi, dtype=np.int64),
        model.options.model_dump(), settings.solver_backend,
        None if size.request_memory is None else float(size.request_memory))
