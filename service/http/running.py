"""Run one task for a synchronous request: submit, wait with a timeout, free the worker when
the client leaves, count the outcome."""

from __future__ import annotations

import asyncio
from typing import Any

from starlette.requests import ClientDisconnect, Request
from starlette.responses import Response

from service.api.task import TaskRequest, TaskResult
from service.backends import errors as backend
from service.backends.contracts import Executor
from service.http.metrics import ServiceMetrics
from service.http.problems import problem_for


async def run_task(request: Request, task: TaskRequest, executor: Executor,
                   metrics: ServiceMetrics, timeout: float) -> TaskResult:
    """Submit a task and wait for its result.

    The task carries the deadline (:meth:`TaskRequest.with_deadline`): its refinement stops
    in time to answer its best shape so far rather than a 504. A client that hangs up
    cancels the task (:class:`ClientDisconnect`).

    Args:
        request: The HTTP request (watched for a disconnect).
        task: The task.
        executor: The backend's executor.
        metrics: Where the task's outcome and stage timings are counted.
        timeout: The longest wait in seconds (FFS_REQUEST_TIMEOUT).

    Returns:
        The task's result.

    Raises:
        ProblemError: 503 (queue full, pool down), 504 (timeout: the task is cancelled and
            its worker replaced), 500 (worker died), or the task's own problem (422, 413, ...).
    """
    operation = task.operation
    task = task.with_deadline(timeout)
    try:
        handle = await executor.submit(task)
    except backend.QueueFullError as exc:
        metrics.observe_task(operation, None, "rejected")
        raise problem_for(exc) from None
    try:
        result = await _result_or_disconnect(request, handle.future, timeout)
    except TimeoutError:
        await executor.cancel(handle.id)
        metrics.observe_task(operation, None, "timeout")
        raise problem_for(backend.DeadlineError(
            f"no result within {timeout:g} s (FFS_REQUEST_TIMEOUT); submit large inputs as "
            "a job (POST /v1/jobs)")) from None
    except (ClientDisconnect, asyncio.CancelledError):  # client gone or server stopping
        await executor.cancel(handle.id)  # free the worker: nobody will read the result
        metrics.observe_task(operation, None, "disconnected")
        raise
    except backend.BackendError as exc:
        problem = problem_for(exc)
        metrics.observe_task(operation, None, "error" if problem.status < 500 else "failed")
        raise problem from None
    metrics.observe_task(operation, result, "ok")
    return result


async def _wait_disconnect(request: Request) -> None:
    """Return when the client closes the connection (the body has been read already, so the
    server's next ``receive`` message is ``http.disconnect``)."""
    while True:
        message = await request.receive()
        if message["type"] == "http.disconnect":
            return


async def _result_or_disconnect(request: Request, future: asyncio.Future[Any],
                                timeout: float) -> Any:
    """``future``'s result; TimeoutError after ``timeout`` s; ClientDisconnect as soon as the
    client hangs up (uvicorn does not cancel the request when the client leaves)."""
    watcher = asyncio.ensure_future(_wait_disconnect(request))
    try:
        done, _ = await asyncio.wait({future, watcher}, timeout=timeout,
                                     return_when=asyncio.FIRST_COMPLETED)
    finally:
        watcher.cancel()
    if future in done:
        return future.result()
    if watcher in done:
        raise ClientDisconnect()
    raise TimeoutError


def server_timing(timings: dict[str, float] | None) -> dict[str, str]:
    """The ``Server-Timing`` header of a worker's stage timings.

    Args:
        timings: Seconds per stage, or None.

    Returns:
        ``{"Server-Timing": "<stage>;dur=<ms>, ..."}``, or no header without timings.
    """
    if not timings:
        return {}
    return {"Server-Timing": ", ".join(f"{stage};dur={seconds * 1000:.1f}"
                                       for stage, seconds in timings.items())}


def result_response(result: TaskResult, status_code: int = 200) -> Response:
    """The response of a task's result.

    Args:
        result: The body the worker encoded, its media type and timings.
        status_code: The HTTP status.

    Returns:
        The response, with its ``Server-Timing``.
    """
    return Response(result.body, status_code=status_code, media_type=result.media_type,
                    headers=server_timing(result.timings))
