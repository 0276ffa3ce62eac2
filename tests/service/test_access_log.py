"""The access log of ``python -m service`` (the README's command, a real uvicorn) keeps API
calls, pages and failed requests and leaves out the page's static files (issue 43: 926
lines in one short session); FFS_ACCESS_LOG_STATIC=true puts them back."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.helpers import REPO
from tests.helpers.servers import free_port, stop_process, wait_ready


def _session_log(tmp_path: Path, **env: str) -> str:
    """Start ``python -m service``, make a page-like session of requests, stop it; its log."""
    port = free_port()
    full_env = {**os.environ, "FFS_PORT": str(port), "FFS_WORKERS": "1",
                "FFS_LOG_LEVEL": "info", "PYTHONUNBUFFERED": "1", **env}
    full_env["PYTHONPATH"] = str(REPO)
    log = tmp_path / f"service-{port}.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "service"], cwd=REPO, env=full_env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as http:
                wait_ready(http.get, 1)
                assert http.get("/").status_code in (200, 503)
                for path in ("/static/js/main.js", "/static/style.css", "/favicon.ico"):
                    assert http.get(path).status_code == 200, path
                assert http.get("/static/js/nothere.js").status_code == 404
                triangle = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}
                assert http.post("/v1/forms", json=triangle).status_code == 200
        finally:
            stop_process(proc)
    return log.read_text()


@pytest.fixture(scope="module")
def default_log(tmp_path_factory: pytest.TempPathFactory) -> str:
    return _session_log(tmp_path_factory.mktemp("access"))


def test_api_calls_pages_and_failures_are_logged(default_log: str) -> None:
    assert '"POST /v1/forms HTTP/1.1" 200' in default_log, default_log
    assert '"GET / HTTP/1.1"' in default_log
    assert '"GET /static/js/nothere.js HTTP/1.1" 404' in default_log  # a failure stays


def test_static_files_are_not_logged(default_log: str) -> None:
    for path in ("/static/js/main.js", "/static/style.css", "/favicon.ico"):
        assert f'"GET {path} HTTP/1.1"' not in default_log, default_log


def test_the_setting_logs_them_again(tmp_path: Path) -> None:
    log = _session_log(tmp_path, FFS_ACCESS_LOG_STATIC="true")
    assert '"GET /static/js/main.js HTTP/1.1" 200' in log, log
    assert '"POST /v1/forms HTTP/1.1" 200' in log
