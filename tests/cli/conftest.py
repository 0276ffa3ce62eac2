"""Fixtures of the command-line tests: the ``ffs`` command run as a user runs it (a
subprocess in a temporary folder) and a real uvicorn on loopback for ``--server``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.helpers import DATA, REPO
from tests.helpers.servers import uvicorn_fixture

FFS = shutil.which("ffs")
"""The installed console script (``pip install -e .``); ``python -m ffs`` without it."""

Run = Callable[..., subprocess.CompletedProcess[str]]


server = uvicorn_fixture(
    doc="Base URL of a real uvicorn (2 workers: 1 BLAS thread each on 2 cores).")


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """A temporary folder with a few meshes of tests/data."""
    for name in ("decimated-knight.off", "face.off", "torus.off", "octopus-low-surface.off"):
        shutil.copy(DATA / name, tmp_path / name)
    return tmp_path


@pytest.fixture
def ffs(workdir: Path) -> Run:
    """``ffs(*args)``: the command line in ``workdir``, FFS_SERVER unset, output captured."""

    def run(*args: str, timeout: float = 300, env: dict[str, str] | None = None
            ) -> subprocess.CompletedProcess[str]:
        command = [FFS] if FFS else [sys.executable, "-m", "ffs"]
        full_env = {k: v for k, v in os.environ.items() if k != "FFS_SERVER"}
        full_env["PYTHONPATH"] = os.pathsep.join(
            p for p in (str(REPO), full_env.get("PYTHONPATH", "")) if p)
        return subprocess.run([*command, *args], cwd=workdir, capture_output=True, text=True,
                              timeout=timeout, env={**full_env, **(env or {})})

    return run
