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
from collections.abc import AsyncIterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import anyio
import orjson
from pydantic import BaseModel, ValidationError
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import Request

from service.api.decoding import BINARY_MEDIA_TYPE, MAX_SHAPES
from service.api.problems import (
    ProblemError,
    element_error,
    failure_of,
    from_validation_errors,
)
from service.api.task import MeshFile
from service.memory import release_memory
from service.settings import Settings
from solver.mesh.sniffing import SNIFF_BYTES, leading_bytes, sniff

THREAD_THRESHOLD = 256 * 1024
"""Bodies larger than this are validated in a worker thread, off the event loop."""
MAX_FORM_FILES = MAX_SHAPES + 4
"""Most files one multipart form may carry (spooled as they arrive): a blend's shapes and a
few more, so that a form one file over a blend's limit is still named by its operation."""
PROCESS_THRESHOLD = 4 * 1024 * 1024
"""Bodies larger than this are validated in the parser process instead: orjson holds the GIL
while it parses, so in a thread of this process a 20 MB job body kept the event loop from
answering anything for ~0.5 s."""


def media_type(request: Request) -> str:
    """The request's media type without parameters.

    Args:
        request: The request.

    Returns:
        The lower-case media type (``application/json``).

    Raises:
        ProblemError: 415 when there is none, or when a ``charset`` other than UTF-8 is
            declared (bodies are read as UTF-8 JSON).
    """
    value = request.headers.get("content-type", "")
    mtype, _, params = value.partition(";")
    mtype = mtype.strip().lower()
    if not mtype:
        raise ProblemError("unsupported-media-type", "the request has no Content-Type; send "
                           "application/json, multipart/form-data or " + BINARY_MEDIA_TYPE,
                           errors=[element_error("Content-Type", "missing")])
    for param in params.split(";"):
        key, _, charset = param.partition("=")
        charset = charset.strip().strip('"').lower()
        if key.strip().lower() == "charset" and charset not in ("utf-8", "utf8"):
            raise ProblemError("unsupported-media-type", f"charset={charset} is not supported; "
                               "send UTF-8",
                               errors=[element_error("Content-Type", f"charset {charset}")])
    return mtype


def is_json(mtype: str) -> bool:
    """Whether a media type is plain JSON.

    Args:
        mtype: A media type from :func:`media_type`.

    Returns:
        True for ``application/json`` only (``application/json-patch+json`` and other
        ``+json`` types mean something else: 415).
    """
    return mtype == "application/json"


async def read_body(request: Request, settings: Settings) -> bytearray:
    """The whole body, read within the body limit and timeout.

    The chunks are appended to one buffer as they arrive (never a list of chunks joined
    at the end, which held the body twice), so the body's memory is about its size.

    Args:
        request: The request.
        settings: FFS_MAX_BODY_BYTES and FFS_BODY_TIMEOUT.

    Returns:
        The body (a ``bytearray``: orjson, numpy and pickle read it as they read bytes).

    Raises:
        ProblemError: 413 as soon as it exceeds FFS_MAX_BODY_BYTES (a declared
            Content-Length beyond it before anything is read); 408 (and the connection
            closed) when it takes longer than FFS_BODY_TIMEOUT to arrive.
        ClientDisconnect: The client went away mid-body (answered 499 and logged without
            a traceback by the app's handler).
    """
    body = bytearray()
    async for chunk in _limited_stream(request, settings):
        body += chunk
    return body


async def _limited_stream(request: Request, settings: Settings) -> AsyncIterator[bytes]:
    """The body's chunks as they arrive, within FFS_MAX_BODY_BYTES and FFS_BODY_TIMEOUT.

    Raises:
        ProblemError: as :func:`read_body`.
    """
    limit = settings.max_body_bytes
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise _too_large(int(declared), limit)
    stream = request.stream().__aiter__()
    deadline = asyncio.get_running_loop().time() + settings.body_timeout
    size = 0
    while True:
        try:  # the deadline spans the reads only, never the consumer's work between them
            async with asyncio.timeout_at(deadline):
                chunk = await anext(stream, None)
        except TimeoutError:
            raise ProblemError(
                "body-timeout", f"the body did not arrive within {settings.body_timeout:g} s "
                f"(FFS_BODY_TIMEOUT; {size} bytes received)", headers={"Connection": "close"},
                errors=[element_error("body", f"{size} bytes in {settings.body_timeout:g} s")]
            ) from None
        if chunk is None:
            return
        size += len(chunk)
        if size > limit:
            raise _too_large(size, limit)
        yield chunk


def _too_large(size: int, limit: int) -> ProblemError:
    return ProblemError("payload-too-large",
                        f"the body has at least {size} bytes; the limit is {limit} "
                        "(FFS_MAX_BODY_BYTES)",
                        errors=[element_error("body", f"more than {limit} bytes")])


def validate_object(model: type[BaseModel], data: Any, prefix: tuple[Any, ...] = ()) -> Any:
    """Validate already-parsed data.

    Args:
        model: The pydantic model.
        data: The parsed JSON.
        prefix: Where ``data`` sits in the body; errors point below it.

    Returns:
        The model instance.

    Raises:
        ProblemError: 422 ``validation-error`` naming each error.
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise from_validation_errors(exc.errors(include_url=False),
                                     prefix) from None


async def read_form(request: Request, settings: Settings) -> tuple[dict[str, Any],
                                                                   dict[str, UploadFile]]:
    """Parse a multipart body as it arrives (the files spooled to temporary files beyond
    1 MB, Starlette's ``UploadFile``), never holding it whole in memory.

    Args:
        request: The request (``multipart/form-data``).
        settings: The body limit and timeout.

    Returns:
        ``(fields, files)``: the JSON-decoded form fields (a field given once per item is
        a list) and the uploaded files by field name (a list where the field is repeated:
        the operation decides whether it may be, :func:`service.http.payloads.form_request`).

    Raises:
        ProblemError: 400 ``malformed-request`` for a body that is cut or not multipart;
            the problems of :func:`read_body`, 413 as soon as the body passes the limit.
    """
    closing = b"--" + _boundary(request).encode("latin-1") + b"--"
    tail = bytearray()
    chunks = _limited_stream(request, settings)

    async def receive() -> dict[str, Any]:
        chunk = await anext(chunks, None)
        if chunk is None:
            return {"type": "http.request", "body": b"", "more_body": False}
        tail[:] = (tail + chunk)[-len(closing) - 4:]  # the closing boundary and a CRLF
        return {"type": "http.request", "body": chunk, "more_body": True}

    def cut_off() -> ProblemError | None:  # a cut upload would read as a form without its file
        if bytes(tail).rstrip(b"\r\n").endswith(closing):
            return None
        return ProblemError("malformed-request", "the multipart body ends before its closing "
                            "boundary (the upload was cut off)",
                            errors=[element_error("body", "no closing boundary")])

    streamed = Request(request.scope, receive)  # files spooled to disk beyond 1 MB
    try:
        form = await streamed.form(max_files=MAX_FORM_FILES, max_fields=64,
                                   max_part_size=settings.max_body_bytes)
    except ProblemError:
        raise
    except StarletteHTTPException as exc:
        if "too many files" in str(exc.detail).lower():  # Starlette's words for max_files
            raise _too_many_files() from None
        raise cut_off() or ProblemError(
            "malformed-request", f"cannot read the multipart body: {exc.detail}") from None
    except Exception:  # python-multipart parse errors (their text names internals)
        raise cut_off() or ProblemError(
            "malformed-request", "cannot read the multipart body: it is not well-formed "
            "multipart/form-data") from None
    if problem := cut_off():
        await form.close()
        raise problem
    fields: dict[str, Any] = {}
    files: dict[str, UploadFile | list[UploadFile]] = {}
    repeated: set[str] = set()
    for key, value in form.multi_items():
        is_file = isinstance(value, UploadFile)
        if key in (fields if is_file else files):  # a field both a file and a value
            raise ProblemError("malformed-request", f"form field {key!r} is given twice",
                               errors=[element_error(key, "repeated")])
        if is_file:
            previous = files.get(key)
            files[key] = (value if previous is None else
                          [*(previous if isinstance(previous, list) else [previous]), value])
        elif key in fields:  # one part per item: how generated clients send an array
            if key not in repeated:
                fields[key] = [fields[key]]
                repeated.add(key)
            fields[key].append(_decode_field(value))
        else:
            fields[key] = _decode_field(value)
    return fields, files


def _too_many_files() -> ProblemError:
    """The 422 of a form with more than :data:`MAX_FORM_FILES` files: only ``blend``'s
    ``shapes`` takes more than one, as many as the library's blend does."""
    return ProblemError(
        "validation-error", f"shapes: the form has more than {MAX_FORM_FILES} files; a blend "
        f"takes 1 to {MAX_SHAPES} (one `shapes` part per mesh), the other operations one "
        "file per field", errors=[element_error("shapes", f"at most {MAX_SHAPES} files",
                                                type="too_long")])


def as_arrays(model: type[BaseModel], fields: dict[str, Any]) -> dict[str, Any]:
    """Form fields with a single value of an array field as a one-item array.

    An array comes as one JSON part (``[...]``) or as one part per item (:func:`read_form`).

    Args:
        model: The params model the fields are for.
        fields: The form fields.

    Returns:
        ``fields``, each array field of ``model`` a list.
    """
    arrays = array_fields(model)
    return {name: [value] if name in arrays and not isinstance(value, list) else value
            for name, value in fields.items()}


def array_fields(model: type[BaseModel]) -> frozenset[str]:
    """The array fields of a model.

    Args:
        model: A pydantic model.

    Returns:
        The names of its ``list[...]`` fields (optionally ``| None``).
    """
    names = set()
    for name, info in model.model_fields.items():
        members = [a for a in typing.get_args(info.annotation) or (info.annotation,)
                   if a is not type(None)]
        if typing.get_origin(info.annotation) is list or (
                typing.get_origin(info.annotation) in (typing.Union, types.UnionType)
                and all(typing.get_origin(a) is list for a in members)):
            names.add(name)
    return frozenset(names)


def _boundary(request: Request) -> str:
    """The multipart boundary of the request's Content-Type (a 400 problem without one)."""
    for param in request.headers.get("content-type", "").split(";")[1:]:
        key, _, value = param.partition("=")
        if key.strip().lower() == "boundary" and value.strip().strip('"'):
            return value.strip().strip('"')
    raise ProblemError("malformed-request", "the multipart Content-Type has no boundary",
                       errors=[element_error("Content-Type", "no boundary")])


def _decode_field(value: str) -> Any:
    """Form values are JSON (``{"a": 1}``, ``[1, 2]``, ``0.5``, ``true``) or plain strings."""
    try:
        return orjson.loads(value)
    except orjson.JSONDecodeError:
        return value


async def upload(file: UploadFile, field: str) -> MeshFile:
    """Read one uploaded mesh file, after a look at its first bytes.

    The first :data:`~solver.mesh.sniffing.SNIFF_BYTES` are read and checked against the
    format the file's name (or media type) gives (:func:`solver.mesh.sniffing.sniff`)
    before the whole file is read, once, into memory for its worker: a file that cannot be
    that format is refused at submission, a job included, however large it is.

    Args:
        file: The upload (spooled by :func:`read_form`).
        field: Its form field.

    Returns:
        The file for the worker (its bytes, its name or media type, the field).

    Raises:
        ProblemError: 415 ``unsupported-file-type`` for an unknown type, 400
            ``unreadable-file`` for an empty file or one whose start is not its format's.
    """
    from solver.core.errors import UnsupportedFormatError
    from solver.mesh.formats import LOAD_FORMATS, resolve_format

    name = file.filename or ""
    given = name if "." in name else (file.content_type or name)
    try:
        fmt = resolve_format(given)
    except UnsupportedFormatError as exc:
        raise ProblemError(
            "unsupported-file-type",
            f"{field}: {name or file.content_type!r} is not a supported mesh file; upload "
            f"one of {', '.join(LOAD_FORMATS)}",
            errors=[element_error(field, exc.reason)]) from None
    head = await file.read(SNIFF_BYTES)
    if not head:
        raise ProblemError("unreadable-file", f"{field}: the file is empty",
                           errors=[element_error(field, "empty file")])
    size = file.size if file.size is not None else len(head)
    if problem := sniff(fmt, head, size):
        raise ProblemError(
            "unreadable-file", f"{field}: {name or given!r} does not read as {fmt.upper()}: "
            f"{problem}; its first bytes: '{leading_bytes(head)}'",
            errors=[element_error(field, problem, value=name or given, format=fmt,
                                  starts=leading_bytes(head))])
    if size > len(head) or file.size is None:
        await file.seek(0)
        return MeshFile(await file.read(), given, field)  # the whole file, read once
    return MeshFile(head, given, field)


class ParserPool:
    """The process that validates the largest bodies, started and stopped with the backend.

    :meth:`start` opens it (the app's lifespan, :meth:`service.http.dependencies.Services.start`);
    its one process is started on the first body over :data:`PROCESS_THRESHOLD` and replaced
    when it dies; :meth:`stop` ends it, after which a large body is answered 503.
    """

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self._open = False
        self._lock = threading.Lock()

    def start(self) -> None:
        """Accept work (the process itself starts with the first large body)."""
        with self._lock:
            self._open = True

    def stop(self) -> None:
        """End the parser process (blocking, at most ~2 s).

        A body being validated is abandoned: its request is being answered 503 by the
        stopping server.
        """
        with self._lock:
            pool, self._pool, self._open = self._pool, None, False
        if pool is None:
            return
        processes = list(getattr(pool, "_processes", {}).values())  # no public handle on them
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.kill()
        for process in processes:
            process.join(2.0)

    def pids(self) -> list[int]:
        """The process ids of the parser (none before the first large body, or after stop)."""
        with self._lock:
            return list(getattr(self._pool, "_processes", None) or ())

    async def run(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` in the parser process (``fn``, its arguments and result must pickle).

        Args:
            fn: A module-level function.
            *args: Its arguments.

        Returns:
            What ``fn`` returned.

        Raises:
            ProblemError: What ``fn`` raised, as its problem (:func:`failure_of`), or 503
                ``unavailable`` when the process died while validating, or is stopped.
        """
        pool = self._running()
        try:
            future = pool.submit(_parse_remotely, fn, *args)  # raises if it died while idle
            outcome, value = await asyncio.wrap_future(future)
        except BrokenProcessPool:  # it died (e.g. killed for memory): the next body gets a new one
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            raise ProblemError("unavailable", "the process that validates large bodies died "
                                              "while validating this one; retry") from None
        if outcome == "failed":
            raise ProblemError.from_dict(value)
        return value

    def _running(self) -> ProcessPoolExecutor:
        with self._lock:
            if not self._open:
                raise ProblemError("unavailable", "the service is not running (starting or "
                                   "stopping); retry", headers={"Retry-After": "5"})
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    1, mp_context=multiprocessing.get_context("forkserver"))
            return self._pool


async def off_loop(parser: ParserPool, size: int, fn: Any, *args: Any) -> Any:
    """Run ``fn(*args)`` where its input's size allows without stalling the event loop.

    Args:
        parser: The app's parser process.
        size: The input's size in bytes.
        fn: The parse; it and its arguments and result must pickle.
        *args: Its arguments.

    Returns:
        What ``fn`` returned: computed here when the input is small, in a thread when it is
        larger than THREAD_THRESHOLD bytes (then the memory of the parse is given back to
        the system before answering), in ``parser`` when it is larger than
        PROCESS_THRESHOLD.
    """
    if size <= THREAD_THRESHOLD:
        return fn(*args)
    if size > PROCESS_THRESHOLD:
        try:
            return await parser.run(fn, *args)
        finally:
            release_memory()  # the pickled copy of the body sent to the parser
    result, error = await anyio.to_thread.run_sync(_capture, fn, *args)
    gc.collect()
    release_memory()
    if error is not None:
        raise error
    return result


def _parse_remotely(fn: Any, *args: Any) -> tuple[str, Any]:
    """``fn(*args)`` in the parser process, then its heap goes back.

    Returns:
        ``("ok", result)`` or ``("failed", failure dict)`` (:func:`failure_of`, the workers'
        own picklable form of an error).
    """
    try:
        return "ok", fn(*args)
    except Exception as exc:
        return "failed", failure_of(exc)
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


OPERATION_MEDIA_TYPES = ("application/json", "multipart/form-data with the mesh in `file`",
                         BINARY_MEDIA_TYPE)
"""What an operation's endpoint takes (``POST /v1/forms``, ...), in words."""


def unsupported_media_type(mtype: str, accepted: Sequence[str] = OPERATION_MEDIA_TYPES
                           ) -> ProblemError:
    """The 415 problem of a media type an endpoint does not take.

    Args:
        mtype: The request's media type.
        accepted: The media types this endpoint takes, in words (default: an operation's).

    Returns:
        The problem, naming the media types it takes.

    Example:
        >>> unsupported_media_type("text/plain", ("application/json",)).detail
        "Content-Type 'text/plain' is not supported; send application/json"
    """
    *rest, last = accepted
    takes = f"{', '.join(rest)}, or {last}" if len(rest) > 1 else " or ".join([*rest, last])
    return ProblemError("unsupported-media-type",
                        f"Content-Type {mtype!r} is not supported; send {takes}",
                        errors=[element_error("Content-Type", mtype)])
