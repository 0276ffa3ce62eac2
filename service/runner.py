"""Run one task on the executor for a synchronous request, with timeout and error mapping."""

from __future__ import annotations

import asyncio
from typing import Any

from starlette.requests import Request
from starlette.responses import Response

from service.executor import (
    ExecutorClosedError,
    QueueFullError,
    TaskCancelledError,
    TaskFailedError,
    WorkerDiedError,
)
from service.jobs import queue_full_problem
from service.problems import ProblemError, from_worker_error


async def run_task(request: Request, operation: str, payload: dict[str, Any]) -> dict[str, Any]:
    """Submit ``operation`` and wait up to FFS_REQUEST_TIMEOUT for its result.

    Raises problems: 503 (queue full / pool down), 504 (timeout: the task is cancelled and
    its worker replaced), 500 (worker died), or the task's own problem (422, 413, ...).
    """
    state = request.app.state
    executor, metrics = state.executor, state.metrics
    timeout = state.settings.request_timeout
    try:
        handle = await executor.submit(operation, payload)
    except QueueFullError as exc:
        metrics.observe_task(operation, None, "rejected")
        raise queue_full_problem(exc) from None
    except ExecutorClosedError as exc:
        raise ProblemError("unavailable", str(exc), headers={"Retry-After": "5"}) from None
    try:
        result = await asyncio.wait_for(asyncio.shield(handle.future), timeout)
    except TimeoutError:
        await executor.cancel(handle.id)
        metrics.observe_task(operation, None, "timeout")
        raise ProblemError("timeout", f"no result within {timeout:g} s (FFS_REQUEST_TIMEOUT); "
                           "submit large inputs as a job (POST /v1/jobs)") from None
    except asyncio.CancelledError:  # client gone or server stopping: free the worker
        await executor.cancel(handle.id)
        raise
    except TaskFailedError as exc:
        problem = from_worker_error(exc.error)
        metrics.observe_task(operation, None, "error" if problem.status < 500 else "failed")
        raise problem from None
    except WorkerDiedError as exc:
        metrics.observe_task(operation, None, "failed")
        raise ProblemError("worker-died", exc.reason) from None
    except (TaskCancelledError, ExecutorClosedError) as exc:
        raise ProblemError("unavailable", f"the task was stopped: {exc}",
                           headers={"Retry-After": "5"}) from None
    metrics.observe_task(operation, result, "ok")
    return result


def server_timing(timings: dict[str, float] | None) -> dict[str, str]:
    """A ``Server-Timing`` header with the worker's stage timings (milliseconds)."""
    if not timings:
        return {}
    return {"Server-Timing": ", ".join(f"{stage};dur={seconds * 1000:.1f}"
                                       for stage, seconds in timings.items())}


def result_response(result: dict[str, Any], status_code: int = 200) -> Response:
    """The encoded body produced by the worker."""
    return Response(result["body"], status_code=status_code, media_type=result["media_type"],
                    headers=server_timing(result.get("timings")))
