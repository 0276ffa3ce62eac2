"""The README's "Command line" and "Python client" examples run as written (from a folder
with the repository's tests/data), in-process and against a real uvicorn standing in for
http://127.0.0.1:8000."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.helpers import REPO

FFS = shutil.which("ffs")

README_URL = "http://127.0.0.1:8000"


def section(title: str) -> str:
    text = (REPO / "README.md").read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end]


def blocks(title: str, language: str) -> list[str]:
    found = re.findall(rf"```{language}\n(.*?)```", section(title), flags=re.S)
    assert found, f"README section {title!r} has no {language} example"
    return found


def test_readme_command_line_examples_run(tmp_path: Path, server: str):
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(REPO / "tests" / "data")
    script = "set -euo pipefail\n"
    if not FFS:
        script += f'ffs() {{ "{sys.executable}" -m ffs "$@"; }}\n'
    script += "\n".join(blocks("Command line", "bash")).replace(README_URL, server)
    env = {k: v for k, v in os.environ.items() if k != "FFS_SERVER"}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    result = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True,
                            text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    for name in ("knight-forms.json", "knight.glb", "face-flat.obj", "face-report.json",
                 "torus-uv.obj",
                 "face-deformed.ply", "blend/face-0.25.ply", "blend/face-0.75.ply",
                 "converted/torus.ply", "forms/face.npz", "rebuilt/decimated-knight.ply",
                 "rebuilt.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    from solver.mesh.io import load_mesh_file

    V, _ = load_mesh_file(REPO / "tests" / "data" / "face.off")
    W, _ = load_mesh_file(tmp_path / "face-deformed.ply")
    # The example is scaled to the face (181 units wide): vertex 500 lifted by 3 units.
    np.testing.assert_allclose(W[[0, 500]], V[[0, 500]] + [[0, 0, 0], [0, 0, 3]], atol=1e-5)
    assert np.abs(W - V).max() > 0.1
    assert "warning" not in result.stderr  # the examples' answers are within the thresholds


def test_readme_python_client_example_runs(server: str, capsys):
    code = blocks("Python client", "python")[0].replace(README_URL, server)
    cwd = os.getcwd()
    os.chdir(REPO)
    try:
        namespace: dict = {}
        exec(compile(code, "README.md", "exec"), namespace)
    finally:
        os.chdir(cwd)
    assert namespace["bent"].report["refinement"]["refined"] is True
    assert namespace["flat"].uv.shape == (1180, 2)
    assert namespace["moved"].shape == (502, 3)
    out = capsys.readouterr().out
    assert "index-out-of-range /faces/0" in out
