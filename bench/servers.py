"""Servers for the benchmarks: a real uvicorn running the service, and a Dask cluster started
with the same commands as docker-compose.yml (``dask scheduler --preload service.backends.dask``,
``dask worker ... --nthreads 1``), all on loopback."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator

import httpx

from bench.common import REPO
from tests.helpers.servers import free_port, stop_process


def _env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1",
           "UVICORN_WS_PER_MESSAGE_DEFLATE": "false", **(extra or {})}  # as in the image
    return env


@contextlib.contextmanager
def uvicorn(env: dict[str, str], workers_ready: int = 1) -> Iterator[str]:
    """``uvicorn service.app:app`` on a free port with ``env``; yields the base URL."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "service.app:app", "--host",
                             "127.0.0.1", "--port", str(port), "--log-level", "warning"],
                            cwd=REPO, env=_env(env), start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise RuntimeError(f"uvicorn exited with {proc.returncode}")
            with contextlib.suppress(httpx.TransportError):
                ready = httpx.get(f"{base}/readyz", timeout=2)
                if ready.status_code == 200 and ready.json()["workers_ready"] >= workers_ready:
                    break
            time.sleep(0.1)
        else:
            raise RuntimeError("the service did not become ready")
        yield base
    finally:
        stop_process(proc, timeout=20)


@contextlib.contextmanager
def dask_cluster(n_workers: int) -> Iterator[str]:
    """A Dask scheduler and ``n_workers`` single-threaded worker processes; yields the
    scheduler address."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = _env({"DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "1",
                "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"})
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
         "--port", str(port), "--dashboard-address", ":0", "--preload", "service.backends.dask"],
        cwd=REPO, env=env, start_new_session=True, **quiet)
    workers = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers",
         str(n_workers), "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard"],
        cwd=REPO, env=env, start_new_session=True, **quiet)
    try:
        from distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(n_workers, timeout=120)
        yield address
    finally:
        stop_process(workers, timeout=20)
        stop_process(scheduler, timeout=20)

