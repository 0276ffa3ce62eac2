"""The worker pool: bounded queue (503), timeouts (504), worker death, cancellation."""

from __future__ import annotations

import asyncio
import itertools
import os
import signal
import threading
import time

import numpy as np
import pytest

from service.backends.errors import (
    ExecutorClosedError,
    QueueFullError,
    TaskCancelledError,
    TaskFailedError,
    WorkerDiedError,
)
from service.backends.local.executor import ProcessExecutor
from tests.helpers.aio import run as run_async
from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app
from tests.helpers.service import debug_task, forms_json, forms_task, mesh_json, problem


def _submit(client, task, **params):
    return client.portal.call(client.app.state.services.backend.executor.submit,
                              debug_task(task, **params))


def test_queue_full_is_503_with_retry_after():
    with running_app(workers=1, queue_size=1) as c:
        busy = _submit(c, "debug.sleep", seconds=30)
        waiting = _submit(c, "debug.sleep", seconds=30)
        assert c.get("/readyz").json() == {"status": "ready", "workers": 1, "workers_ready": 1,
                                           "busy": 1, "queue_depth": 1}
        response = c.post("/v1/forms", json=mesh_json(*icosphere(0)))
        doc = problem(response, 503, "queue-full")
        assert int(response.headers["retry-after"]) >= 1
        assert doc["retry_after"] == int(response.headers["retry-after"])
        job = c.post("/v1/jobs", json={"operation": "forms", "input": mesh_json(*icosphere(0))})
        problem(job, 503, "queue-full")
        metrics = c.get("/metrics").text
        assert "ffs_queue_depth 1.0" in metrics and "ffs_pool_busy_workers 1.0" in metrics
        executor = c.app.state.services.backend.executor
        for handle in (waiting, busy):
            assert c.portal.call(executor.cancel, handle.id)
        deadline = time.monotonic() + 30
        while c.get("/readyz").json()["workers_ready"] < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert c.post("/v1/forms", json=mesh_json(*icosphere(0))).status_code == 200


def test_sync_timeout_is_504_and_frees_the_worker():
    with running_app(workers=1, request_timeout=0.05) as c:
        executor = c.app.state.services.backend.executor
        pid = executor.worker_pids()[0]
        # ~1 s of work, far beyond the 50 ms timeout, on a mesh small enough that its first
        # answer is predicted within it (a larger mesh is refused 413 use-a-job unrun)
        V, F = icosphere(3)
        body = {"vertices_a": V.tolist(), "vertices_b": (V * [1.0, 1.0, 1.5]).tolist(),
                "faces": F.tolist(), "t": np.linspace(0, 1, 64).tolist()}
        doc = problem(c.post("/v1/interpolate", json=body), 504, "timeout")
        assert "FFS_REQUEST_TIMEOUT" in doc["detail"]
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            ready = c.get("/readyz").json()
            if ready["workers_ready"] == 1 and executor.worker_pids() != [pid]:
                break
            time.sleep(0.05)
        assert executor.worker_pids() != [pid]  # the abandoned solve was stopped
        assert executor.restarts == 1
        assert 'ffs_tasks_total{operation="interpolate",outcome="timeout"} 1.0' in c.get(
            "/metrics").text


def test_sync_request_whose_worker_dies_is_500_and_the_pool_recovers(client):
    executor = client.app.state.services.backend.executor
    V, F = icosphere(6)  # ~2.5 s: factorize (icosphere(5) takes 0.6 s on a quiet machine)
    body = {**forms_json(V, F), "options": {"exact_shortcut": False}}
    result = {}

    def call():
        result["response"] = client.post("/v1/reconstruct", json=body)

    thread = threading.Thread(target=call)
    thread.start()
    deadline = time.monotonic() + 30
    while executor.busy() == 0 and time.monotonic() < deadline:
        time.sleep(0.002)
    busy = [w.pid for w in list(executor._workers.values()) if w.task is not None]
    assert busy, "the request never reached a worker"
    time.sleep(0.3)  # let it start solving (about 2.5 s of work)
    os.kill(busy[0], signal.SIGKILL)
    thread.join(60)
    doc = problem(result["response"], 500, "worker-died")
    assert "SIGKILL" in doc["detail"]
    deadline = time.monotonic() + 30
    while client.get("/readyz").json()["workers_ready"] < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert client.post("/v1/forms", json=mesh_json(*icosphere(1))).status_code == 200


def test_process_executor_directly():
    async def scenario():
        executor = ProcessExecutor(2, 1, start_method="forkserver", threads_per_worker=1)
        with pytest.raises(ExecutorClosedError):
            await executor.submit(debug_task("debug.sleep", seconds=0))
        await executor.start()
        try:
            events = []
            handle = await executor.submit(
                debug_task("debug.sleep", seconds=0.05, steps=5),
                progress_cb=lambda stage, f: events.append((stage, f)),
                on_start=lambda: events.append(("start", 0.0)))
            result = await handle.future
            assert result.body == b'{"slept": true}' and "solve" in result.timings
            assert events[0] == ("start", 0.0)
            # 6 reports in 0.05 s: the first and the last (PROGRESS_INTERVAL)
            assert [f for _, f in events[1:]] == [0.0, 1.0]

            failing = await executor.submit(debug_task("debug.raise", message="kaput"))
            with pytest.raises(TaskFailedError) as info:
                await failing.future
            assert info.value.error["kind"] == "internal-error"
            assert info.value.error["status"] == 500
            assert "kaput" not in str(info.value.error)  # logged in the worker, not shown

            crash = await executor.submit(debug_task("debug.crash", code=7))
            with pytest.raises(WorkerDiedError, match="exit code 7"):
                await crash.future

            a = await executor.submit(debug_task("debug.sleep", seconds=30))
            b = await executor.submit(debug_task("debug.sleep", seconds=30))
            c = await executor.submit(debug_task("debug.sleep", seconds=30))
            with pytest.raises(QueueFullError):
                await executor.submit(debug_task("debug.sleep", seconds=30))
            assert executor.queue_depth() >= 1
            for handle in (c, b, a):
                assert await executor.cancel(handle.id)
                with pytest.raises(TaskCancelledError):
                    await handle.future
            assert not await executor.cancel(a.id)

            deadline = time.monotonic() + 30
            while executor.workers_ready() < 2 and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            again = await executor.submit(forms_task(*icosphere(0)))
            assert (await again.future).media_type == "application/json"
            pending = await executor.submit(debug_task("debug.sleep", seconds=30))
        finally:
            await executor.shutdown()
        with pytest.raises(ExecutorClosedError):
            await pending.future
        assert executor.worker_pids() == []

    run_async(scenario())


def test_local_worker_progress_is_throttled_and_ends_at_1():
    """A task reporting 2000 times in about a second (an atlas reports every chart) sends
    a few reports over the local worker's pipe, PROGRESS_INTERVAL apart, the first (0) and
    the last (1) among them, in order; the job record of that task ends at 1."""
    from service.backends.jobs import Job
    from service.worker.runtime import PROGRESS_INTERVAL

    async def scenario():
        executor = ProcessExecutor(1, 1, start_method="forkserver", threads_per_worker=1)
        await executor.start()
        try:
            events: list[tuple[float, str, float]] = []
            job = Job("x", "forms")
            started = time.monotonic()

            def progress(stage: str, fraction: float) -> None:
                events.append((time.monotonic(), stage, fraction))
                job.update_progress(stage, fraction)

            handle = await executor.submit(debug_task("debug.sleep", seconds=1.0, steps=2000),
                                           progress_cb=progress)
            await handle.future
            elapsed = time.monotonic() - started
        finally:
            await executor.shutdown()
        fractions = [f for _, _, f in events]
        assert fractions[0] == 0.0 and fractions[-1] == 1.0, fractions
        assert fractions == sorted(fractions) and {s for _, s, _ in events} == {"solve"}
        assert 3 <= len(events) <= elapsed / PROGRESS_INTERVAL + 2, (len(events), elapsed)
        gaps = [b[0] - a[0] for a, b in itertools.pairwise(events[:-1])]  # the last: flushed
        assert min(gaps) > PROGRESS_INTERVAL / 2, gaps  # arrival jitter: half the interval
        assert job.stages["solve"] == 1.0

    run_async(scenario())


def test_a_worker_starts_with_the_file_readers_imported():
    """The readers defer trimesh (~0.4 s to import); a worker imports it while warming, so
    its first upload does not pay that within the request's deadline (CI saw a 20,480-face
    PLY answered 504 at FFS_REQUEST_TIMEOUT=0.55 instead of 413 ``use-a-job``)."""
    import subprocess
    import sys

    script = ("import sys\n"
              "from service.worker import runtime\n"
              "before = 'trimesh' in sys.modules\n"
              "runtime.initialize_worker(1)\n"
              "print(before, 'trimesh' in sys.modules)\n")
    from tests.helpers import REPO

    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True, cwd=REPO).stdout.split()
    assert out == ["False", "True"]
