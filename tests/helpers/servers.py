"""Servers for the tests and the benchmarks: a free loopback port, a process stopped
cleanly, an in-process app (Starlette's TestClient, lifespan and worker pool included) and a
real uvicorn on a free loopback port (also as a pytest fixture)."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

with warnings.catch_warnings():  # "install httpx2": the TestClient still uses httpx here
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

from tests.helpers import REPO

STARTUP_TIMEOUT = 60.0


def wait_ready(get: Callable[[str], Any], workers: int, timeout: float = STARTUP_TIMEOUT) -> None:
    """Poll /readyz until ``workers`` workers are up."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        with contextlib.suppress(httpx.TransportError):
            last = get("/readyz")
            if last.status_code == 200 and last.json()["workers_ready"] >= workers:
                return
        time.sleep(0.05)
    raise AssertionError(f"service not ready after {timeout} s: {last and last.text}")


@contextlib.contextmanager
def running_app(**overrides: Any) -> Iterator[TestClient]:
    """An app with ``Settings(**overrides)``, its lifespan running, all workers ready."""
    from service.app import create_app  # here: the benchmarks import this module too
    from service.settings import Settings

    settings = Settings(**{"workers": 2, **overrides})
    app = create_app(settings)
    with TestClient(app, raise_server_exceptions=False) as client:
        wait_ready(client.get, settings.workers)
        yield client


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS's choice)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stop_process(proc: subprocess.Popen[bytes], timeout: float = 15.0) -> None:
    """SIGTERM ``proc`` (started with ``start_new_session=True``) and wait ``timeout``
    seconds for it; then SIGKILL its whole process group."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)


@contextlib.contextmanager
def uvicorn_server(env: dict[str, str] | None = None) -> Iterator[str]:
    """Real uvicorn (``python -m uvicorn service.app:app``) on a free loopback port."""
    with uvicorn_process(env) as (base, _):
        yield base


@contextlib.contextmanager
def uvicorn_process(env: dict[str, str] | None = None, log_level: str = "warning",
                    ) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """:func:`uvicorn_server`, also yielding the server process (its pid, for psutil); its
    output goes to :func:`server_log` (``log_level`` ``info`` adds uvicorn's access log)."""
    port = free_port()
    full_env = {**os.environ, "FFS_WORKERS": "2", "PYTHONUNBUFFERED": "1", **(env or {})}
    full_env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(REPO), full_env.get("PYTHONPATH", "")) if p)
    log = (REPO / "tests" / "artifacts")
    log.mkdir(parents=True, exist_ok=True)
    with open(log / f"uvicorn-{port}.log", "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "service.app:app", "--host", "127.0.0.1",
             "--port", str(port), "--log-level", log_level,
             "--http", "service.http.server:HeaderTimeoutProtocol"],
            cwd=REPO, env=full_env, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True)
        base = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(base_url=base, timeout=10) as http:
                def get(path: str) -> httpx.Response:
                    if proc.poll() is not None:
                        raise AssertionError(f"uvicorn exited with {proc.returncode}: "
                                             + (log / f"uvicorn-{port}.log").read_text())
                    return http.get(path)

                wait_ready(get, int(full_env["FFS_WORKERS"]))
            yield base, proc
        finally:
            stop_process(proc)


def server_log(base: str) -> Path:
    """The file a :func:`uvicorn_process` at ``base`` writes its output to."""
    return REPO / "tests" / "artifacts" / f"uvicorn-{base.rsplit(':', 1)[1]}.log"


def uvicorn_fixture(env: dict[str, str] | None = None, *, scope: str = "session",
                    doc: str = "") -> Any:
    """A pytest fixture yielding the base URL of :func:`uvicorn_server` with ``env``, for a
    conftest to assign to the fixture's name (``server = uvicorn_fixture()``)."""
    import pytest  # here: the benchmarks import this module without pytest installed

    def fixture() -> Iterator[str]:
        with uvicorn_server(env) as base:
            yield base

    fixture.__doc__ = doc or f"Base URL of a real uvicorn on loopback (environment {env})."
    return pytest.fixture(scope=scope)(fixture)  # type: ignore[call-overload]
