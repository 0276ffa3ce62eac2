"""Graceful shutdown of ``python -m service`` (issue 24, finding 3): SIGTERM while a job
runs ends the service's whole process tree (forkserver, resource tracker, workers, the
parser process), and after a restart the job's id is answered 410 ``job-lost``, as
docs/service.md says (jobs live in memory; running ones are cancelled at shutdown)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import httpx
import numpy as np
import psutil

from tests.helpers import REPO
from tests.helpers.meshes import icosphere
from tests.helpers.servers import free_port, wait_ready
from tests.helpers.service import forms_json, problem


@contextlib.contextmanager
def _service(port: int, log_name: str, **env_vars: str) -> Iterator[subprocess.Popen[bytes]]:
    """``python -m service`` on ``port`` (``env_vars`` added to its environment); killed (its
    process group) if the test fails."""
    env = {**os.environ, "FFS_PORT": str(port), "FFS_WORKERS": "2", "PYTHONUNBUFFERED": "1",
           **env_vars}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    logs = REPO / "tests" / "artifacts"
    logs.mkdir(parents=True, exist_ok=True)
    with open(logs / log_name, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "service"], cwd=REPO, env=env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as http:
                wait_ready(http.get, 2)
            yield proc
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(15)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)  # whatever the test found left over
            proc.wait(5)


def _alive(pids: list[int]) -> list[str]:
    out = []
    for pid in pids:
        with contextlib.suppress(psutil.NoSuchProcess):
            process = psutil.Process(pid)
            if process.status() != psutil.STATUS_ZOMBIE:
                out.append(f"{pid}: {' '.join(process.cmdline())[:100]}")
    return out


def test_sigterm_during_a_job_ends_every_process_and_the_job_is_lost_after_a_restart():
    V, F = icosphere(6)  # 81,920 faces, bent angles: a refined reconstruct of seconds
    forms = forms_json(V, F)
    forms["angles"] = (np.asarray(forms["angles"]) * 0.8).tolist()
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    with _service(port, "shutdown-first.log") as proc:
        submitted = httpx.post(f"{base}/v1/jobs", json={"operation": "reconstruct",
                                                        "input": forms}, timeout=60)
        assert submitted.status_code == 202, submitted.text
        location = submitted.headers["location"]
        deadline = time.monotonic() + 30
        while httpx.get(base + location).json()["status"] != "running":
            assert time.monotonic() < deadline, "the job never started"
            time.sleep(0.05)
        tree = [proc.pid, *(c.pid for c in psutil.Process(proc.pid).children(recursive=True))]
        assert len(tree) >= 5, tree  # tracker, forkserver, two workers (and the parser)
        stopped = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(10)
        while _alive(tree) and time.monotonic() - stopped < 10:
            time.sleep(0.1)
        assert not _alive(tree), _alive(tree)

    with _service(port, "shutdown-second.log"):
        lost = httpx.get(base + location)
        doc = problem(lost, 410, "job-lost")
        assert "restarted" in doc["detail"] and doc["restarted_at"].endswith("Z"), doc
        assert problem(httpx.get(f"{base}/v1/jobs/{'0' * 32}"), 404, "not-found")
        for method in ("DELETE",):
            problem(httpx.request(method, base + location), 410, "job-lost")
        problem(httpx.get(base + location + "/result"), 410, "job-lost")


def test_sigterm_exits_with_status_0_and_leaves_no_temporary_folder(tmp_path):
    """uvicorn raises the SIGTERM it caught again after its graceful shutdown; a death by it
    skipped the interpreter's exit handlers and left multiprocessing's forkserver socket
    folder (``pymp-*``) in the temporary folder at every stop of the service."""
    with _service(free_port(), "shutdown-tmpdir.log", TMPDIR=str(tmp_path)) as proc:
        assert [p.name for p in tmp_path.glob("pymp-*")], "the forkserver made no folder"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
    assert list(tmp_path.iterdir()) == []
