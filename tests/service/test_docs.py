"""docs/service.md: its curl and Python examples run against a real server; its settings table
lists every setting."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys

import httpx
import numpy as np
import pytest

from service.settings import ENV_PREFIX, Settings
from tests.helpers import REPO
from tests.helpers.servers import free_port, wait_ready

DOC = REPO / "docs" / "service.md"
BLOCK = re.compile(r"```(bash|python|yaml)\n(.*?)```", re.DOTALL)


def _blocks(language):
    return [code for lang, code in BLOCK.findall(DOC.read_text(encoding="utf-8"))
            if lang == language]


def test_settings_table_lists_every_setting():
    text = DOC.read_text(encoding="utf-8")
    for name in Settings.model_fields:
        assert f"`{ENV_PREFIX}{name.upper()}`" in text, name


def test_python_client_example_is_ten_lines():
    httpx_example = _blocks("python")[0]
    assert "import httpx" in httpx_example
    assert len(httpx_example.strip().splitlines()) <= 10


@pytest.fixture
def workdir(tmp_path):
    (tmp_path / "tests").symlink_to(REPO / "tests")
    return tmp_path


def test_curl_examples(live_server, workdir):
    blocks = [b for b in _blocks("bash") if "curl" in b]
    assert len(blocks) >= 5
    for code in blocks:
        script = code.replace("http://localhost:8000", live_server)
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=workdir,
                              capture_output=True, text=True, timeout=120, check=False)
        assert proc.returncode == 0, f"{code}\nstdout: {proc.stdout}\nstderr: {proc.stderr}"
    for glb in ("face.glb", "torus.glb", "face-deformed.glb", "torus-mesh.glb"):
        assert (workdir / glb).read_bytes()[:4] == b"glTF", glb
    assert b'"integrable":true' in (workdir / "knight-report.json").read_bytes()
    assert len((workdir / "knight.json").read_bytes()) > 1000
    flat = json.loads((workdir / "face-flat.json").read_bytes())
    assert len(flat["uv"]) == 1180 and flat["flipped_faces"] == []
    blend = json.loads((workdir / "face-blend.json").read_bytes())
    assert blend["t"] == [0.0, 0.5, 1.0] and len(blend["vertices"]) == 3
    assert len(blend["refinement"]) == 3
    deformed = json.loads((workdir / "face-deformed.json").read_bytes())
    np.testing.assert_allclose(blend["vertices"][0], _off_vertices(REPO / "tests" / "data" /
                                                                   "face.off"), atol=1e-6)
    np.testing.assert_allclose(deformed["vertices"][500], [0, 0, 1], atol=1e-6)


def _off_vertices(path):
    words = path.read_text().split()
    n = int(words[1])
    return np.asarray(words[4:4 + 3 * n], dtype=float).reshape(n, 3)


def _run_python(code, live_server, cwd):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(cwd), str(REPO)])}
    proc = subprocess.run([sys.executable, "-c", code.replace("http://localhost:8000",
                                                              live_server)],
                          cwd=cwd, capture_output=True, text=True, timeout=120, check=False,
                          env=env)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_python_example(live_server, workdir):
    defect, count = _run_python(_blocks("python")[0], live_server, workdir).split()
    assert float(defect) > 1e-3 and int(count) == 642


def test_generated_client_example(live_server, workdir):
    """The documented configuration and command, then the generated client's example."""
    (config,) = _blocks("yaml")
    (workdir / "openapi-python-client.yaml").write_text(config, encoding="utf-8")
    (workdir / "openapi").symlink_to(REPO / "openapi")
    (command,) = [b for b in _blocks("bash") if "openapi-python-client generate" in b]
    proc = subprocess.run(["bash", "-euo", "pipefail", "-c", command], cwd=workdir,
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (example,) = [b for b in _blocks("python") if "fundamental_forms_service_client" in b]
    status, *_, size = _run_python(example, live_server, workdir).split()
    assert status == "succeeded" and int(size) > 1000


def test_serve_example():
    """The Serve block starts the service (on a free port) and it answers."""
    (code,) = [b for b in _blocks("bash") if "python -m service" in b]
    port = free_port()
    script = code.replace("FFS_PORT=8000", f"FFS_PORT={port}").replace("FFS_HOST=0.0.0.0",
                                                                       "FFS_HOST=127.0.0.1")
    env = {**os.environ, "FFS_WORKERS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(["bash", "-c", script], cwd=REPO, env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_ready(lambda path: httpx.get(f"http://127.0.0.1:{port}{path}", timeout=5), 1)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=60)
