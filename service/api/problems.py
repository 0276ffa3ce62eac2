"""Problems: the failures a client caused or must know about, with their kinds.

A :class:`ProblemError` carries a problem ``kind`` (a key of :data:`PROBLEM_KINDS`, which
gives its status and title), a ``detail`` and ``errors`` items naming the offending
elements (:func:`element_error`). Workers raise it, backends' failures are converted to it,
and the HTTP edge (:mod:`service.http.problems`) renders it as an RFC 9457 document::

    {"type": "/problems/index-out-of-range", "title": "Index out of range", "status": 422,
     "detail": "faces[17]: index 9001 out of range [0, 100)", "instance": "/v1/forms",
     "kind": "index-out-of-range",
     "errors": [{"field": "faces", "index": 17, "reason": "index 9001 out of range [0, 100)"}]}

Every exception becomes a problem in one place, :func:`problem_of`: a
:class:`solver.core.errors.SolverInputError` is the problem of its ``kind`` (422 for the array
checks, 400 ``unreadable-file``, 415 ``unsupported-file-type``, 422 ``singular-system`` and
``invalid-option``) naming its element, anything unexpected a 500 that shows nothing of it.
A failure leaves a worker process as a plain dict, "a failure": the problem document
without its ``instance`` (:func:`failure_of` for an exception, :func:`failure` for a kind);
:meth:`ProblemError.from_dict` turns it back into the problem.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from solver.core.errors import ERROR_KINDS, SolverInputError

PROBLEM_BASE = "/problems/"

PROBLEM_KINDS: dict[str, tuple[int, str, str]] = {
    # Service-level kinds: kind -> (status, title, description).
    "validation-error": (422, "Request does not match the schema",
                         "A field is missing, has the wrong type, is not finite (NaN or "
                         "infinity) or is out of its allowed range; `errors` names each one."),
    "malformed-json": (400, "Malformed JSON", "The body is not valid JSON."),
    "malformed-request": (400, "Malformed request",
                          "The multipart body or a form field could not be read."),
    "unreadable-file": (400, "Unreadable mesh file",
                        "The uploaded mesh file could not be parsed."),
    "unsupported-media-type": (415, "Unsupported media type",
                               "Send application/json (UTF-8), multipart/form-data or "
                               "application/vnd.ffs.arrays, as the endpoint documents."),
    "unsupported-file-type": (415, "Unsupported mesh file type",
                              "Upload an OBJ, PLY, OFF, STL or GLB file."),
    "payload-too-large": (413, "Request body too large",
                          "The body exceeds FFS_MAX_BODY_BYTES."),
    "header-timeout": (408, "Request head too slow",
                       "The request headers did not arrive within FFS_HEADER_TIMEOUT seconds; "
                       "the connection is closed."),
    "body-timeout": (408, "Request body too slow",
                     "The body did not arrive within FFS_BODY_TIMEOUT seconds; the connection "
                     "is closed."),
    "mesh-too-large": (413, "Mesh too large",
                       "The mesh exceeds FFS_MAX_VERTICES or FFS_MAX_FACES, or its operation's "
                       "predicted peak memory exceeds FFS_MAX_REQUEST_MEMORY."),
    "use-a-job": (413, "Too large for a synchronous request",
                  "The mesh's answer is predicted to take longer than FFS_REQUEST_TIMEOUT "
                  "allows a synchronous request: submit the same input as a job "
                  "(POST /v1/jobs), which has FFS_JOB_TIMEOUT."),
    "blend-too-large": (413, "Blend too large",
                        "Rows x vertices of the blend exceed FFS_MAX_BLEND_VERTICES: send "
                        "fewer rows per request (or a coarser mesh)."),
    "not-acceptable": (406, "Not acceptable",
                       "None of the media types in Accept can be produced for this result."),
    "unsupported-color": (422, "Colour field not available",
                          "The requested vertex colour field is not produced by this operation."),
    "invalid-option": (422, "Invalid option", "An option has a value the solver cannot use."),
    "not-integrable": (422, "Forms are not integrable",
                       "options.require_integrable is set and the integrability check failed; "
                       "`errors` names the worst vertices."),
    "singular-system": (422, "Singular linear system",
                        "The constraints leave the linear system singular or ill-posed."),
    "forbidden-origin": (403, "Origin not allowed",
                         "The request came from a web page of another origin; the service "
                         "accepts its own origin and those in FFS_CORS_ORIGINS."),
    "not-found": (404, "Not found", "No such resource (or the job expired)."),
    "method-not-allowed": (405, "Method not allowed", "The path does not accept this method."),
    "job-lost": (410, "Job lost in a restart",
                 "The job was submitted before the service restarted; jobs live in memory "
                 "and running ones are cancelled when the service stops. Submit it again."),
    "job-not-finished": (409, "Job not finished", "The job is still queued or running."),
    "job-failed": (409, "Job failed", "The job failed; `error` holds its problem document."),
    "job-cancelled": (409, "Job cancelled", "The job was cancelled; it has no result."),
    "color-not-computed": (409, "Colour not computed",
                           "Submit the job with that `color` to fetch its result coloured."),
    "queue-full": (503, "Server busy", "The work queue is full; retry after Retry-After seconds."),
    "too-many-jobs": (503, "Too many jobs",
                      "FFS_MAX_JOBS jobs are queued or running (finished ones give way to new "
                      "ones); retry later."),
    "too-many-client-jobs": (429, "Too many jobs from this client",
                             "This client has FFS_MAX_CLIENT_JOBS jobs queued or running; "
                             "wait for one to finish."),
    "unavailable": (503, "Service unavailable", "The worker pool is not running."),
    "too-many-sessions": (429, "Too many sessions",
                          "FFS_MAX_SESSIONS deformation sessions are open and none has "
                          "been idle for FFS_SESSION_GIVE_WAY seconds; retry after "
                          "Retry-After seconds."),
    "too-many-client-sessions": (429, "Too many sessions from this client",
                                 "This client has FFS_MAX_CLIENT_SESSIONS sessions open; "
                                 "delete one or let one expire."),
    "session-memory": (503, "Session memory exhausted",
                       "The open sessions and this one would exceed FFS_MAX_SESSION_MEMORY."),
    "drag-superseded": (409, "Drag superseded",
                        "A newer drag of the session replaced this one: only the newest "
                        "drag is refined. `latest` is its number; fetch its refined shape."),
    "session-gone": (410, "Session gone",
                     "The session expired (FFS_SESSION_TTL) or the worker holding it died; "
                     "`reason` says which. Create a new session."),
    "timeout": (504, "Timed out", "The result was not ready within FFS_REQUEST_TIMEOUT."),
    "worker-died": (500, "Worker died", "The worker process running the request exited."),
    "internal-error": (500, "Internal error", "An unexpected error; it has been logged."),
    "http-error": (400, "HTTP error", "A generic HTTP error."),
    "unauthorized": (401, "API key required",
                     "The service requires an API key (`Authorization: Bearer <key>`) and "
                     "the request had none, or one it does not know."),
    "forbidden": (403, "Not allowed for this key",
                  "The key's role may not do this (e.g. `/metrics` needs an admin key)."),
    "rate-limited": (429, "Too many requests for this key",
                     "The key used its requests of the current minute; retry after "
                     "Retry-After seconds (RateLimit and RateLimit-Policy say more)."),
    "quota-exceeded": (429, "Quota of this key exceeded",
                       "The key has as many jobs or sessions as its quota allows; wait for "
                       "one to finish or close one."),
}
for _cls in ERROR_KINDS:
    PROBLEM_KINDS[_cls.kind] = (422, _cls.kind.replace("-", " ").capitalize(),
                                (_cls.__doc__ or "").strip().splitlines()[0])
PROBLEM_KINDS[SolverInputError.kind] = (422, "Invalid input", "Invalid input data.")
INTERNAL_DETAIL = "the solver failed unexpectedly; the error has been logged"
"""The ``detail`` of a task's unexpected failure (its cause is in the worker's log)."""
logger = logging.getLogger("service.worker")


MAX_PROBLEM_ERRORS = 20
"""Most ``errors`` items a problem document lists; ``errors_omitted`` counts the rest."""
MAX_TEXT = 400
"""Longest ``detail`` or ``reason`` text, in characters (then an ellipsis and a count)."""
_NUMPY_SCALAR = re.compile(r"\bnp\.(?:float|int|uint|bool_?)\d*\(([^()]*)\)")
_EXCEPTION_NAME = re.compile(r"\b(?:[A-Z][A-Za-z]*(?:Error|Exception)|Traceback[^:]*): ")


_CUT = re.compile(r"\.\.\. \(\d+ more characters\)")


def in_words(text: str) -> str:
    """A text as a client should read it.

    Args:
        text: A detail or reason.

    Returns:
        ``text`` with numpy scalar reprs as plain numbers (``np.float64(-1.0)`` ->
        ``-1.0``), no exception class names, and at most MAX_TEXT characters (then an
        ellipsis and the count of the rest); a text already shortened stays as it is.
    """
    text = _EXCEPTION_NAME.sub("", _NUMPY_SCALAR.sub(r"\1", text))
    if len(text) > MAX_TEXT and not _CUT.fullmatch(text, MAX_TEXT):
        text = f"{text[:MAX_TEXT]}... ({len(text) - MAX_TEXT} more characters)"
    return text


def element_error(field: str | None, reason: str, index: int | None = None,
                  **context: Any) -> dict[str, Any]:
    """One item of a problem's ``errors``: the element at fault and why.

    Args:
        field: The input at fault (``"faces"``, ``"Content-Type"``, a form field), or None.
        reason: Why, in words.
        index: The row of ``field`` at fault, or None when the whole input is.
        **context: Further JSON-ready members (``value``, ``pointer``, ``type``, ``line``).

    Returns:
        ``{"field", "index", "reason", **context}``.

    Example:
        >>> element_error("Content-Type", "missing")
        {'field': 'Content-Type', 'index': None, 'reason': 'missing'}
    """
    return {"field": field, "index": index, "reason": reason, **context}


def _capped(errors: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The first MAX_PROBLEM_ERRORS items, their texts in words and long lists cut."""
    items = []
    for error in errors[:MAX_PROBLEM_ERRORS]:
        item = dict(error)
        for key, value in item.items():
            if isinstance(value, str):
                item[key] = in_words(value)
            elif isinstance(value, list | tuple) and len(value) > MAX_PROBLEM_ERRORS:
                item[key] = list(value[:MAX_PROBLEM_ERRORS])  # e.g. every face of a mesh
        items.append(item)
    return items


def problem_type(kind: str) -> str:
    """The ``type`` URI of a problem kind.

    Args:
        kind: A key of :data:`PROBLEM_KINDS`.

    Returns:
        ``/problems/<kind>``.
    """
    return PROBLEM_BASE + kind


class ProblemError(Exception):
    """An error that the app's handler turns into a problem document.

    Args:
        kind: The problem kind (a key of :data:`PROBLEM_KINDS`).
        detail: A human-readable explanation of this occurrence (in words: :func:`in_words`).
        status: The HTTP status; by default the kind's.
        errors: Items naming the elements at fault (:func:`element_error`); the first
            MAX_PROBLEM_ERRORS are kept and ``errors_omitted`` counts the rest.
        headers: Extra response headers (e.g. Retry-After).
        **extensions: Extra top-level members of the document.

    Attributes:
        kind: The problem kind.
        status: The HTTP status.
        detail: The explanation.
        errors: The items, capped.
        headers: The extra response headers.
        extensions: The extra top-level members.
    """

    def __init__(self, kind: str, detail: str, *, status: int | None = None,
                 errors: Sequence[Mapping[str, Any]] | None = None,
                 headers: Mapping[str, str] | None = None, **extensions: Any) -> None:
        detail = in_words(detail)
        super().__init__(detail)
        self.kind = kind
        self.status = status or PROBLEM_KINDS.get(kind, (500,))[0]
        self.detail = detail
        errors = list(errors or [])
        self.errors = _capped(errors)
        self.headers = dict(headers or {})
        if len(errors) > MAX_PROBLEM_ERRORS:
            extensions = {**extensions, "errors_omitted": len(errors) - MAX_PROBLEM_ERRORS}
        self.extensions = extensions

    def to_dict(self, instance: str | None = None) -> dict[str, Any]:
        """The problem document.

        Args:
            instance: The request path it answers, if any.

        Returns:
            ``{"type", "title", "status", "detail", "kind", "instance"?, "errors",
            **extensions}``.
        """
        title = PROBLEM_KINDS.get(self.kind, (0, "Error"))[1]
        doc: dict[str, Any] = {"type": problem_type(self.kind), "title": title,
                               "status": self.status, "detail": self.detail, "kind": self.kind}
        if instance:
            doc["instance"] = instance
        doc["errors"] = self.errors
        doc.update(self.extensions)
        return doc

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> ProblemError:
        """The problem of a document made by :meth:`to_dict`: a failure a worker sent, a
        stored job error.

        Args:
            doc: The document (its ``instance``, ``type`` and ``title`` are ignored).

        Returns:
            The problem, with the document's status, errors and extensions.
        """
        known = {"type", "title", "status", "detail", "kind", "instance", "errors"}
        return cls(str(doc.get("kind", "internal-error")), str(doc.get("detail", "")),
                   status=int(doc.get("status", 500)), errors=doc.get("errors"),
                   **{k: v for k, v in doc.items() if k not in known})


# ----------------------------------------------------------------------------- conversions


def problem_of(exc: BaseException) -> ProblemError:
    """The problem an exception answers with: the one conversion of errors to problems.

    Args:
        exc: What a task, a parser or a route raised.

    Returns:
        ``exc`` itself for a :class:`ProblemError`; for a
        :class:`~solver.core.errors.SolverInputError` the problem of its ``kind`` (its status
        from :data:`PROBLEM_KINDS`) whose ``detail`` is the error's message and whose one
        ``errors`` item is :meth:`~solver.core.errors.SolverInputError.element`; 413
        ``mesh-too-large`` for a :class:`MemoryError`; otherwise a 500 ``internal-error``
        that shows nothing of it (``exc`` is logged here, with its traceback).
    """
    if isinstance(exc, ProblemError):
        return exc
    if isinstance(exc, SolverInputError):
        kind = exc.kind if exc.kind in PROBLEM_KINDS else SolverInputError.kind
        return ProblemError(kind, str(exc), errors=[exc.element()])
    if isinstance(exc, MemoryError):
        return ProblemError("mesh-too-large", "the input needs more memory than is available")
    logger.error("task failed: %s: %s", type(exc).__name__, exc, exc_info=exc)
    return ProblemError("internal-error", INTERNAL_DETAIL, status=500)


def use_a_job(n_faces: int, max_sync_faces: int, seconds: float, field: str) -> ProblemError:
    """The 413 ``use-a-job`` problem of a synchronous request predicted to miss its deadline.

    Args:
        n_faces: The mesh's face count.
        max_sync_faces: The most faces whose answer is predicted within ``seconds``.
        seconds: What FFS_REQUEST_TIMEOUT leaves the solver.
        field: The input the mesh came in.

    Returns:
        The problem: its ``detail`` says how to submit the request as a job; ``job`` is the
        path to submit it to.
    """
    reason = (f"{n_faces} faces exceed the {max_sync_faces} faces whose answer is predicted "
              f"within the {seconds:.0f} s a synchronous request has (FFS_REQUEST_TIMEOUT)")
    return ProblemError(
        "use-a-job", reason + "; submit it as a job: POST /v1/jobs with {\"operation\": "
        "<this endpoint's operation>, \"input\": <this body>} (or this multipart upload "
        "with an \"operation\" field), then GET its Location until it is done",
        errors=[element_error(field, reason)], job="/v1/jobs")


def failure_of(exc: BaseException) -> dict[str, Any]:
    """The failure dict a worker sends for an exception (picklable, JSON-ready).

    Args:
        exc: What the task raised.

    Returns:
        The document of :func:`problem_of` (``exc``) without an ``instance``; read back
        with :meth:`ProblemError.from_dict`.
    """
    return problem_of(exc).to_dict()


def failure(kind: str, detail: str, **extensions: Any) -> dict[str, Any]:
    """The failure dict of a problem ``kind`` (how backends record e.g. a job's timeout).

    Args:
        kind: A key of :data:`PROBLEM_KINDS`.
        detail: What happened, in words.
        **extensions: Further top-level members of the document.

    Returns:
        The problem document without an ``instance``, as :func:`failure_of` makes them.
    """
    return ProblemError(kind, detail, **extensions).to_dict()


def pointer_from_loc(loc: Iterable[Any]) -> dict[str, Any]:
    """Map a pydantic error location to ``{"field", "index", "pointer"}``.

    Args:
        loc: The location; union tags such as ``list[float]`` are dropped.

    Returns:
        The field (names joined by dots), the first list index and the JSON pointer.

    Example:
        >>> where = pointer_from_loc(("constraints", "positions", 2, "vertex"))
        >>> where["field"], where["index"], where["pointer"]
        ('constraints.positions.vertex', 2, '/constraints/positions/2/vertex')
    """
    parts = [p for p in loc if not (isinstance(p, str) and ("[" in p or p in _UNION_TAGS))]
    names = [str(p) for p in parts if isinstance(p, str)]
    indices = [p for p in parts if isinstance(p, int)]
    return {"field": ".".join(names) or None, "index": indices[0] if indices else None,
            "pointer": "/" + "/".join(str(p) for p in parts) if parts else ""}


_UNION_TAGS = {"float", "int", "str", "bool", "function-after", "function-before",
               "constrained-float", "constrained-int", "constrained-str"}


def from_validation_errors(errors: Sequence[Mapping[str, Any]], prefix: Sequence[Any] = (),
                           limit: int = 50) -> ProblemError:
    """The 422 ``validation-error`` of pydantic errors.

    Args:
        errors: Pydantic's errors (``exc.errors()``).
        prefix: Where the validated data sits in the body (``("input",)`` for a job).
        limit: The most errors listed.

    Returns:
        The problem, its detail naming the first error, its items each error's pointer,
        reason and type.
    """
    items, quotes = [], []
    for err in errors[:limit]:
        loc = (*prefix, *err.get("loc", ()))
        item = pointer_from_loc(loc)
        item["reason"] = _PYTHON_DICT.sub("a JSON object", str(err.get("msg", "invalid")))
        item["type"] = str(err.get("type", ""))
        if (quote := quoted_value(err)) is not None:
            item["value"] = quote.value
        items.append(item)
        quotes.append(quote)
    first = items[0] if items else {"field": None, "reason": "invalid"}
    where = first["field"] or "body"
    if first.get("index") is not None:
        where += f"[{first['index']}]"
    sent = f" (sent: {quotes[0].text})" if quotes and quotes[0] is not None else ""
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return ProblemError("validation-error", f"{where}: {first['reason']}{sent}{more}",
                        status=422, errors=items)


_PYTHON_DICT = re.compile(r"a valid dictionary( or instance of \w+)?")
"""Pydantic's Python words for an object ("a valid dictionary or instance of HandleTarget",
a class of ours): the client sent JSON, so it reads "a JSON object"."""

_UNQUOTED_TYPES = {"missing", "extra_forbidden"}
"""Pydantic error types whose ``input`` is not the value at fault (the parent object)."""

_NON_FINITE = ("NaN", "Infinity", "-Infinity")
"""How a non-finite number is quoted (JSON has no literal for it)."""

MAX_QUOTED_CHARS = 80
"""Longest string value a problem quotes (longer ones are cut, with an ellipsis)."""


@dataclass(frozen=True)
class Quote:
    """The value a validation error is about, quoted once for both places it shows: the
    ``errors`` item's ``value`` and the problem's ``detail`` (``(sent: ...)``).

    Attributes:
        value: JSON-ready (a non-finite number as the string JSON has no literal for).
        bare: ``value`` stands for a non-finite number: the detail writes it without
            quotes (``NaN``, where the string ``"NaN"`` is quoted).
    """

    value: Any
    bare: bool = False

    @property
    def text(self) -> str:
        """The value as the detail writes it: as JSON, a non-finite number bare."""
        return str(self.value) if self.bare else json.dumps(self.value, ensure_ascii=False)


def quoted_value(error: Mapping[str, Any]) -> Quote | None:
    """The value a validation error is about, or None when it is not worth quoting.

    Only scalars are quoted (a number, a string cut to :data:`MAX_QUOTED_CHARS`, a
    boolean, null); a non-finite number as the string JSON has no literal for.

    Example:
        >>> quoted_value({"type": "greater_than", "input": -5})
        Quote(value=-5, bare=False)
        >>> nan = quoted_value({"type": "finite_number", "input": float("nan")})
        >>> nan.value, nan.text, quoted_value({"type": "x", "input": "NaN"}).text
        ('NaN', 'NaN', '"NaN"')
    """
    if "input" not in error or error.get("type") in _UNQUOTED_TYPES:
        return None
    value = error["input"]
    if isinstance(value, float) and not math.isfinite(value):
        return Quote(_NON_FINITE[0] if math.isnan(value) else _NON_FINITE[1 if value > 0 else 2],
                     bare=True)
    if isinstance(value, str):
        return Quote(value if len(value) <= MAX_QUOTED_CHARS
                     else value[:MAX_QUOTED_CHARS] + "…")
    if value is None or isinstance(value, bool | int | float):
        return Quote(value)
    return None
