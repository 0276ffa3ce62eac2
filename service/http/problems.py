"""Problems at the HTTP edge: RFC 9457 responses, the app's error handlers, and the one
mapping from backend failures to problems.

Every error response is an ``application/problem+json`` document
(:meth:`service.api.problems.ProblemError.to_dict`); ``GET /problems/{kind}`` describes
each kind. :func:`problem_for` is where the backends' domain errors
(:mod:`service.backends.errors`) and task failures become problems, so no backend knows
about HTTP; a solver error raised in this process becomes its problem by
:func:`service.api.problems.problem_of`, as in a worker.
"""

from __future__ import annotations

import logging
from typing import Any

import orjson
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.responses import Response
from starlette.routing import Match

from service.api.problems import ProblemError, from_validation_errors, problem_of
from service.backends import errors as backend
from solver.core.errors import SolverInputError

logger = logging.getLogger("service")

PROBLEM_MEDIA_TYPE = "application/problem+json"
CLIENT_CLOSED = 499
"""Status recorded (never seen by anyone) when the client disconnected before the answer."""
RETRY_SOON = {"Retry-After": "5"}


def problem_for(exc: backend.BackendError) -> ProblemError:
    """The problem a backend failure answers with.

    Args:
        exc: The backend's failure; a :class:`~service.backends.errors.TaskFailedError`
            carries the task's failure dict.

    Returns:
        The problem (its status, detail, headers such as Retry-After, and extensions).
    """
    if isinstance(exc, backend.TaskFailedError):
        return ProblemError.from_dict(exc.error)  # an internal one was logged where it was
    if isinstance(exc, backend.QueueFullError):
        return ProblemError("queue-full", str(exc),
                            headers={"Retry-After": str(exc.retry_after)},
                            retry_after=exc.retry_after)
    if isinstance(exc, backend.TooManySessionsError):
        return ProblemError("too-many-sessions", str(exc),
                            headers={"Retry-After": str(exc.retry_after)}, limit=exc.limit,
                            count=exc.count, retry_after=exc.retry_after)
    if isinstance(exc, backend.SessionMemoryError):
        return ProblemError("session-memory", str(exc), headers={"Retry-After": "30"},
                            memory_used=exc.used, memory_needed=exc.needed,
                            memory_limit=exc.limit)
    if isinstance(exc, backend.SessionGoneError):
        return ProblemError("session-gone", str(exc), reason=exc.reason)
    if isinstance(exc, backend.SessionNotFoundError | backend.DragNotFoundError):
        return ProblemError("not-found", str(exc))
    if isinstance(exc, backend.DragSupersededError):
        return ProblemError("drag-superseded", str(exc), drag=exc.drag, latest=exc.latest)
    if isinstance(exc, backend.ClientJobsError):
        return ProblemError("too-many-client-jobs", str(exc), headers=RETRY_SOON,
                            limit=exc.limit)
    if isinstance(exc, backend.ClientSessionsError):
        return ProblemError("too-many-client-sessions", str(exc), headers=RETRY_SOON,
                            limit=exc.limit)
    if isinstance(exc, backend.JobLostError):
        return ProblemError("job-lost", str(exc), restarted_at=exc.started_at)
    if isinstance(exc, backend.JobStoreFullError):
        return ProblemError("too-many-jobs", str(exc), headers=RETRY_SOON)
    if isinstance(exc, backend.WorkerDiedError):
        return ProblemError("worker-died", exc.reason)
    if isinstance(exc, backend.DeadlineError):
        return ProblemError("timeout", str(exc))
    if isinstance(exc, backend.TaskCancelledError):
        return ProblemError("unavailable", f"the task was stopped: {exc}", headers=RETRY_SOON)
    return ProblemError("unavailable", str(exc), headers=RETRY_SOON)  # ExecutorClosedError


def problem_response(problem: ProblemError, instance: str | None = None) -> Response:
    """The ``application/problem+json`` response of a problem.

    Args:
        problem: The problem.
        instance: The request path it answers.

    Returns:
        The response, with the problem's status and headers.
    """
    body = orjson.dumps(problem.to_dict(instance), option=orjson.OPT_SERIALIZE_NUMPY,
                        default=_fallback)
    return Response(body, status_code=problem.status, media_type=PROBLEM_MEDIA_TYPE,
                    headers=problem.headers)


def _fallback(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


def allowed_methods(request: Request) -> list[str]:
    """Every method some route of the app serves at the request's path.

    Starlette's 405 names only the first matching route's (``GET`` where ``DELETE`` is
    served too).

    Args:
        request: The request answered 405.

    Returns:
        The methods, in :data:`METHODS` order.
    """
    routes = request.app.router.routes
    return [method for method in METHODS
            if any(route.matches({**request.scope, "method": method})[0] == Match.FULL
                   for route in routes)]


def install_handlers(app: FastAPI) -> None:
    """Register handlers so that every error leaves the app as a problem document.

    Args:
        app: The application.
    """

    async def on_problem(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, ProblemError)
        return problem_response(exc, request.url.path)

    async def on_backend(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, backend.BackendError)
        return problem_response(problem_for(exc), request.url.path)

    async def on_request_validation(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, RequestValidationError)
        return problem_response(from_validation_errors(exc.errors()), request.url.path)

    async def on_pydantic(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, ValidationError)
        return problem_response(from_validation_errors(exc.errors()), request.url.path)

    async def on_solver_error(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, SolverInputError)
        return problem_response(problem_of(exc), request.url.path)

    async def on_http(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, StarletteHTTPException)
        kind = {404: "not-found", 405: "method-not-allowed", 413: "payload-too-large",
                415: "unsupported-media-type"}.get(exc.status_code, "http-error")
        headers = dict(exc.headers or {})
        detail = str(exc.detail)
        if exc.status_code == 405:
            allow = allowed_methods(request)
            headers["Allow"] = ", ".join(allow)
            detail = f"{request.method} is not allowed here; use {', '.join(allow)}"
        problem = ProblemError(kind, detail, status=exc.status_code, headers=headers)
        return problem_response(problem, request.url.path)

    async def on_disconnect(request: Request, exc: Exception) -> Response:
        # The client closed the connection before its body arrived: nobody reads an answer.
        # 499 (nginx's "client closed request") keeps it apart from server errors in metrics.
        logger.info("client disconnected during %s %s", request.method, request.url.path)
        return Response(status_code=CLIENT_CLOSED)

    async def on_unexpected(request: Request, exc: Exception) -> Response:
        logger.exception("unhandled error on %s %s", request.method, request.url.path)
        problem = ProblemError("internal-error", "an unexpected error; it has been logged",
                               status=500)
        return problem_response(problem, request.url.path)

    app.add_exception_handler(ProblemError, on_problem)
    app.add_exception_handler(backend.BackendError, on_backend)
    app.add_exception_handler(RequestValidationError, on_request_validation)
    app.add_exception_handler(ValidationError, on_pydantic)
    app.add_exception_handler(SolverInputError, on_solver_error)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(ClientDisconnect, on_disconnect)
    app.add_exception_handler(Exception, on_unexpected)
