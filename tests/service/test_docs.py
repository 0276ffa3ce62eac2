"""docs/service.md: its curl and Python examples run against a real server; its settings table
lists every setting."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from helpers.service import REPO

from service.settings import ENV_PREFIX, Settings

DOC = REPO / "docs" / "service.md"
BLOCK = re.compile(r"```(bash|python)\n(.*?)```", re.DOTALL)


def _blocks(language):
    return [code for lang, code in BLOCK.findall(DOC.read_text(encoding="utf-8"))
            if lang == language]


def test_settings_table_lists_every_setting():
    text = DOC.read_text(encoding="utf-8")
    for name in Settings.model_fields:
        assert f"`{ENV_PREFIX}{name.upper()}`" in text, name


def test_python_client_example_is_ten_lines():
    (example,) = _blocks("python")
    assert len(example.strip().splitlines()) <= 10


@pytest.fixture
def workdir(tmp_path):
    (tmp_path / "tests").symlink_to(REPO / "tests")
    return tmp_path


def test_curl_examples(live_server, workdir):
    blocks = [b for b in _blocks("bash") if "curl" in b]
    assert len(blocks) >= 3
    for code in blocks:
        script = code.replace("http://localhost:8000", live_server)
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=workdir,
                              capture_output=True, text=True, timeout=120, check=False)
        assert proc.returncode == 0, f"{code}\nstdout: {proc.stdout}\nstderr: {proc.stderr}"
    assert (workdir / "face.glb").read_bytes()[:4] == b"glTF"
    assert (workdir / "torus.glb").read_bytes()[:4] == b"glTF"
    assert b'"integrable":true' in (workdir / "knight-report.json").read_bytes()
    assert len((workdir / "knight.json").read_bytes()) > 1000


def test_python_example(live_server, workdir):
    (example,) = _blocks("python")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", example.replace("http://localhost:8000",
                                                                 live_server)],
                          cwd=workdir, capture_output=True, text=True, timeout=120,
                          check=False, env=env)
    assert proc.returncode == 0, proc.stderr
    defect, count = proc.stdout.split()
    assert float(defect) > 1e-3 and int(count) == 642
