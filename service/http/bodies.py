"""Reading request bodies: media types, the body limit and timeout, multipart forms,
uploaded files, and parsing off the event loop.

Bodies are read here (not by FastAPI) so that one endpoint takes ``application/json``,
``multipart/form-data`` (a mesh file in ``file``, every other field as a JSON-encoded form
value) and ``application/vnd.ffs.arrays`` (the large arrays as raw bytes), and so that the
body limit and the body timeout are enforced while streaming. What a body becomes is
:mod:`service.http.payloads`.
"""

from __future__ import annotations

import asyncio
import gc
import multiprocessing
import threading
import types
import typing
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import anyio
import orjson
from pydantic import BaseModel, ValidationError
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import Request

from service.api.decoding import BINARY_MEDIA_TYPE
from service.api.problems import ProblemError, from_failure, from_validation_errors
from service.api.task import MeshFile
from service.memory import release_memory
from service.settings import Settings
from service.worker.runtime import describe_error

FILE_TYPES = ("obj", "ply", "off", "stl", "glb", "gltf")
THREAD_THRESHOLD = 256 * 1024
"""Bodies larger than this are validated in a worker thread, off the event loop."""
PROCESS_THRESHOLD = 4 * 1024 * 1024
"""Bodies larger than this are validated in the parser process instead: orjson holds the GIL
while it parses, so in a thread of this process a 20 MB job body kept the event loop from
answering anything for ~0.5 s."""


def media_type(request: Request) -> str:
    """The request's media type without parameters; a 415 problem when there is none, or
    when a ``charset`` other than UTF-8 is declared (bodies are read as UTF-8 JSON)."""
    value = request.headers.get("content-type", "")
    mtype, _, params = value.partition(";")
    mtype = mtype.strip().lower()
    if not mtype:
        raise ProblemError("unsupported-media-type", "the request has no Content-Type; send "
                           "application/json, multipart/form-data or " + BINARY_MEDIA_TYPE,
                           errors=[{"field": "Content-Type", "index": None,
                                    "reason": "missing"}])
    for param in params.split(";"):
        key, _, charset = param.partition("=")
        charset = charset.strip().strip('"').lower()
        if key.strip().lower() == "charset" and charset not in ("utf-8", "utf8"):
            raise ProblemError("unsupported-media-type", f"charset={charset} is not supported; "
                               "send UTF-8", errors=[{"field": "Content-Type", "index": None,
                                                      "reason": f"charset {charset}"}])
    return mtype


def is_json(mtype: str) -> bool:
    """Whether the media type is plain JSON (``application/json-patch+json`` and other
    ``+json`` types mean something else: 415)."""
    return mtype == "application/json"


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

    _check_closed(request, body)
    replay = Request(request.scope, receive)
    try:
        form = await replay.form(max_files=4, max_fields=64,
                                 max_part_size=settings.max_body_bytes)
    except StarletteHTTPException as exc:
        raise ProblemError("malformed-request", f"cannot read the multipart body: {exc.detail}"
                           ) from None
    except Exception:  # python-multipart parse errors (their text names internals)
        raise ProblemError("malformed-request", "cannot read the multipart body: it is not "
                           "well-formed multipart/form-data") from None
    fields: dict[str, Any] = {}
    files: dict[str, UploadFile] = {}
    repeated: set[str] = set()
    for key, value in form.multi_items():
        if key in files:
            raise ProblemError("malformed-request", f"form field {key!r} is given twice",
                               errors=[{"field": key, "index": None, "reason": "repeated"}])
        if isinstance(value, UploadFile):
            files[key] = value
        elif key in fields:  # one part per item: how generated clients send an array
            if key not in repeated:
                fields[key] = [fields[key]]
                repeated.add(key)
            fields[key].append(_decode_field(value))
        else:
            fields[key] = _decode_field(value)
    return fields, files


def as_arrays(model: type[BaseModel], fields: dict[str, Any]) -> dict[str, Any]:
    """``fields`` with a single value of an array field of ``model`` as a one-item array: an
    array comes as one JSON part (``[...]``) or as one part per item (:func:`read_form`)."""
    arrays = array_fields(model)
    return {name: [value] if name in arrays and not isinstance(value, list) else value
            for name, value in fields.items()}


def array_fields(model: type[BaseModel]) -> frozenset[str]:
    """The fields of ``model`` that are arrays (``list[...]``, optionally ``| None``)."""
    names = set()
    for name, info in model.model_fields.items():
        members = [a for a in typing.get_args(info.annotation) or (info.annotation,)
                   if a is not type(None)]
        if typing.get_origin(info.annotation) is list or (
                typing.get_origin(info.annotation) in (typing.Union, types.UnionType)
                and all(typing.get_origin(a) is list for a in members)):
            names.add(name)
    return frozenset(names)


def _check_closed(request: Request, body: bytes) -> None:
    """A 400 problem unless the multipart body ends with its closing boundary (a cut upload
    would otherwise read as a form without its file)."""
    boundary = ""
    for param in request.headers.get("content-type", "").split(";")[1:]:
        key, _, value = param.partition("=")
        if key.strip().lower() == "boundary":
            boundary = value.strip().strip('"')
    if not boundary:
        raise ProblemError("malformed-request", "the multipart Content-Type has no boundary",
                           errors=[{"field": "Content-Type", "index": None,
                                    "reason": "no boundary"}])
    if not body.rstrip(b"\r\n").endswith(b"--" + boundary.encode("latin-1") + b"--"):
        raise ProblemError("malformed-request", "the multipart body ends before its closing "
                           "boundary (the upload was cut off)",
                           errors=[{"field": "body", "index": None,
                                    "reason": "no closing boundary"}])


def _decode_field(value: str) -> Any:
    """Form values are JSON (``{"a": 1}``, ``[1, 2]``, ``0.5``, ``true``) or plain strings."""
    try:
        return orjson.loads(value)
    except orjson.JSONDecodeError:
        return value


async def upload(file: UploadFile, field: str) -> MeshFile:
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
    return MeshFile(data, name if "." in name else (file.content_type or name), field)


async def off_loop(size: int, fn: Any, *args: Any) -> Any:
    """Run ``fn(*args)`` in a thread when the input is large (> THREAD_THRESHOLD bytes), then
    give the memory of the parse back to the system before answering; in the parser process
    when it is larger still (> PROCESS_THRESHOLD: ``fn`` and its arguments and result must
    pickle)."""
    if size <= THREAD_THRESHOLD:
        return fn(*args)
    if size > PROCESS_THRESHOLD:
        try:
            return await _in_parser_process(fn, *args)
        finally:
            release_memory()  # the pickled copy of the body sent to the parser
    result, error = await anyio.to_thread.run_sync(_capture, fn, *args)
    gc.collect()
    release_memory()
    if error is not None:
        raise error
    return result


_parser: ProcessPoolExecutor | None = None
_parser_lock = threading.Lock()


def _parser_pool() -> ProcessPoolExecutor:
    """The parser process (one, started on first use, replaced if it dies)."""
    global _parser
    with _parser_lock:
        if _parser is None:
            _parser = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("forkserver"))
        return _parser


def stop_parser() -> None:
    """End the parser process (the app's shutdown; blocking, at most ~2 s): a body being
    validated is abandoned (its request is being answered 503 by the stopping server)."""
    global _parser
    with _parser_lock:
        pool, _parser = _parser, None
    if pool is None:
        return
    processes = list(getattr(pool, "_processes", {}).values())  # no public handle on them
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.kill()
    for process in processes:
        process.join(2.0)


async def _in_parser_process(fn: Any, *args: Any) -> Any:
    """``fn(*args)`` in the parser process; its :class:`ProblemError` is raised here."""
    global _parser
    pool = _parser_pool()
    try:
        future = pool.submit(_parse_remotely, fn, *args)  # raises if it died while idle
        outcome, value = await asyncio.wrap_future(future)
    except BrokenProcessPool:  # it died (e.g. killed for memory): the next body gets a new one
        with _parser_lock:
            if _parser is pool:
                _parser = None
        raise ProblemError("unavailable", "the process that validates large bodies died "
                                          "while validating this one; retry") from None
    if outcome == "failed":
        raise from_failure(value)
    return value


def _parse_remotely(fn: Any, *args: Any) -> tuple[str, Any]:
    """In the parser process: ``fn(*args)`` as ``("ok", result)`` or ``("failed", failure
    dict)`` (:func:`service.worker.runtime.describe_error`, the workers' own picklable form
    of an error); then its heap goes back."""
    try:
        return "ok", fn(*args)
    except Exception as exc:
        return "failed", describe_error(exc)
    finally:
        gc.collect()
        release_memory()


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
