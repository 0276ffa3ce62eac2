"""The client's exceptions: the service's RFC 9457 problem documents as typed errors.

Every failure the service answers with a problem document raises a :class:`ProblemError`
subclass chosen by its status (:data:`PROBLEM_CLASSES`), carrying the document's ``type``,
``title``, ``status``, ``detail``, ``kind`` and ``errors``, and ``pointer``/``field``/
``index``: where the first error points (``"/handles/3/vertex"``, ``faces[17]``)::

    try:
        client.fundamental_forms(vertices, faces)
    except ffs.InvalidInputError as error:
        print(error.kind, error.field, error.index, error.detail)

Failures that never reached an answer are :class:`ServiceUnreachableError` and
:class:`RequestTimeoutError`; a cancelled job's result is :class:`JobCancelledError`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


class FFSError(Exception):
    """Base class of every error the client raises."""


class ServiceUnreachableError(FFSError):
    """The service could not be reached (refused, unknown host, connection dropped)."""


class RequestTimeoutError(FFSError, TimeoutError):
    """No answer within the client's timeout (or a job did not finish in ``wait``'s)."""


class JobCancelledError(FFSError):
    """The job was cancelled; it has no result."""


class LocalFileError(FFSError):
    """A file the client was to send cannot be read: a ``.gltf``'s buffer file beside it
    (:mod:`ffs_wire.gltf`). Its message is ``path: field[index]: reason``.

    Attributes:
        path: the file sent (the ``.gltf``).
        field: ``"buffers"``.
        index: the buffer whose file it is.
        reason: why, in words (``cannot read its file 'box.bin' beside the document (No
            such file or directory)``).
    """

    def __init__(self, path: str, reason: str, *, field: str | None = None,
                 index: int | None = None) -> None:
        self.path, self.reason, self.field, self.index = path, reason, field, index
        where = "" if field is None else (f"{field}[{index}]: " if index is not None
                                          else f"{field}: ")
        super().__init__(f"{path}: {where}{reason}")


class ProblemError(FFSError):
    """A problem document answered by the service.

    Attributes:
        status: HTTP status.
        type: the problem's type URI (``/problems/index-out-of-range``).
        title: the short, kind-wide summary.
        detail: this occurrence, in words.
        kind: the last part of ``type``.
        errors: ``[{"field", "index", "reason", "pointer"?, ...}]``, the offending elements.
        pointer: JSON pointer of the first error (``/handles/3/vertex``), else built from
            its field and index (``/faces/17``), else ``None``.
        field, index: the first error's field and index (``None`` when absent).
        retry_after: seconds from a ``Retry-After`` header, if any.
        document: the whole problem document.
    """

    def __init__(self, document: Mapping[str, Any], status: int | None = None,
                 retry_after: float | None = None) -> None:
        self.document = dict(document)
        self.status = int(status or self.document.get("status") or 0)
        self.type = str(self.document.get("type") or "about:blank")
        self.title = str(self.document.get("title") or "Error")
        self.detail = str(self.document.get("detail") or self.title)
        self.kind = str(self.document.get("kind") or self.type.rsplit("/", 1)[-1])
        errors = self.document.get("errors")
        self.errors: list[dict[str, Any]] = [dict(e) for e in errors or [] if isinstance(e, dict)]
        first = self.errors[0] if self.errors else {}
        self.field: str | None = first.get("field")
        self.index: int | None = first.get("index")
        self.pointer: str | None = first.get("pointer") or _pointer(self.field, self.index)
        self.retry_after = retry_after
        super().__init__(self.detail)

    def __str__(self) -> str:
        return f"{self.detail} ({self.kind}, HTTP {self.status})"


def _pointer(field: str | None, index: int | None) -> str | None:
    if not field:
        return None
    path = "/" + field.replace(".", "/")
    return path if index is None else f"{path}/{index}"


class BadRequestError(ProblemError):
    """400: a malformed body or an unreadable mesh file."""


class UnauthorizedError(ProblemError):
    """401: the service needs an API key (``token=`` / ``FFS_TOKEN`` / ``--token``), or does
    not know the one given."""


class ForbiddenError(ProblemError):
    """403: the key's role does not allow this (e.g. ``/metrics`` needs an admin key)."""


class NotFoundError(ProblemError):
    """404: no such job or session (or it expired)."""


class ConflictError(ProblemError):
    """409: e.g. the result of a job that has not finished."""


class GoneError(ProblemError):
    """410: a session that expired or lost its worker, a job lost in a restart."""


class PayloadTooLargeError(ProblemError):
    """413: the body or the mesh exceeds the service's limits."""


class UnsupportedMediaTypeError(ProblemError):
    """415: a media type or mesh file type the endpoint does not take."""


class InvalidInputError(ProblemError):
    """422: the input names an element the solver or the schema refuses."""


class TooManyRequestsError(ProblemError):
    """429: too many sessions or jobs of this client (``retry_after`` when given)."""


class ServerError(ProblemError):
    """500 and other 5xx answers not listed below."""


class ServiceUnavailableError(ServerError):
    """503: the queue is full or the pool is down (retried by the client first)."""


class GatewayTimeoutError(ServerError):
    """504: the service gave up on the request (``FFS_REQUEST_TIMEOUT``)."""


PROBLEM_CLASSES: dict[int, type[ProblemError]] = {
    400: BadRequestError, 404: NotFoundError, 409: ConflictError, 410: GoneError,
    401: UnauthorizedError, 403: ForbiddenError,
    413: PayloadTooLargeError, 415: UnsupportedMediaTypeError, 422: InvalidInputError,
    429: TooManyRequestsError, 503: ServiceUnavailableError, 504: GatewayTimeoutError,
}
"""HTTP status -> exception class (other 4xx: :class:`ProblemError`, 5xx: ServerError)."""


def problem_error(document: Mapping[str, Any], status: int,
                  retry_after: float | None = None) -> ProblemError:
    """The typed exception of a problem document answered with ``status``."""
    cls = PROBLEM_CLASSES.get(status) or (ServerError if status >= 500 else ProblemError)
    return cls(document, status, retry_after)
