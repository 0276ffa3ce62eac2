"""Run the official Khronos glTF-Validator on bytes, for tests.

The validator is the npm package ``gltf-validator`` (the Dart reference validator compiled to
JavaScript), pinned in ``tools/gltf-validator/package.json`` + ``package-lock.json`` and
installed into ``tools/gltf-validator/node_modules`` (git-ignored) with::

    npm ci --prefix tools/gltf-validator

:func:`ensure_validator_installed` runs that when ``node_modules`` is missing, so a fresh clone
needs only Node >= 18 and npm on PATH (and the npm registry reachable once). The Node entry
point ``tools/gltf-validator/validate.mjs`` reads the asset from stdin and prints the report.

Usage::

    from tests.helpers.gltf_validator import ensure_validator_installed, validate_gltf
    ensure_validator_installed()
    report = validate_gltf(glb_bytes, "glb")
    assert report["issues"]["numErrors"] == 0
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any, Literal

from tests.helpers import REPO

VALIDATOR_DIR = REPO / "tools" / "gltf-validator"
VALIDATE_SCRIPT = VALIDATOR_DIR / "validate.mjs"
_MARKER = VALIDATOR_DIR / "node_modules" / "gltf-validator" / "package.json"

__all__ = ["VALIDATOR_DIR", "ensure_validator_installed", "issue_codes", "validate_gltf"]


class ValidatorUnavailableError(RuntimeError):
    """Node/npm missing, or ``npm ci`` failed."""


def _require(tool: str) -> str:
    path = shutil.which(tool)
    if path is None:
        raise ValidatorUnavailableError(
            f"'{tool}' not found on PATH: the glTF validator needs Node.js >= 18 and npm")
    return path


def ensure_validator_installed(timeout: float = 300.0) -> Path:
    """Install the pinned validator with ``npm ci`` unless already present.

    Returns
    -------
    Path
        The validator folder (``tools/gltf-validator``).

    Raises
    ------
    ValidatorUnavailableError
        If node or npm is missing or the install fails (never silently skipped: CI must run
        the real validator).
    """
    _require("node")
    if not _MARKER.is_file():
        npm = _require("npm")
        proc = subprocess.run(
            [npm, "ci", "--prefix", str(VALIDATOR_DIR), "--no-audit", "--no-fund"],
            cwd=REPO, capture_output=True, text=True, timeout=timeout, check=False)
        if proc.returncode != 0 or not _MARKER.is_file():
            raise ValidatorUnavailableError(
                f"npm ci --prefix {VALIDATOR_DIR} failed (exit {proc.returncode}):\n"
                f"{proc.stdout}\n{proc.stderr}")
    return VALIDATOR_DIR


def validate_gltf(data: bytes, kind: Literal["glb", "gltf"], *, max_issues: int = 0,
                  timeout: float = 120.0) -> dict[str, Any]:
    """Validate a glTF 2.0 asset with the real Khronos validator.

    Parameters
    ----------
    data : bytes
        The whole ``.glb`` file or ``.gltf`` JSON (buffers must be embedded ``data:`` URIs;
        external resources are refused).
    kind : "glb" or "gltf"
        Parse as GLB or as glTF JSON (no format sniffing).
    max_issues : int
        Cap on listed messages; 0 = unlimited.

    Returns
    -------
    dict
        The validator's report: ``report["issues"]`` has ``numErrors``, ``numWarnings``,
        ``numInfos``, ``numHints`` and ``messages`` (each with ``code``, ``message``,
        ``severity`` 0=error .. 3=hint, ``pointer`` or ``offset``); ``report["info"]`` has
        ``totalVertexCount``, ``totalTriangleCount``, ...
    """
    if kind not in ("glb", "gltf"):
        raise ValueError(f"kind must be 'glb' or 'gltf', got {kind!r}")
    ensure_validator_installed()
    proc = subprocess.run(
        [_require("node"), str(VALIDATE_SCRIPT), "--format", kind, "--max-issues",
         str(int(max_issues)), "-"],
        input=data, capture_output=True, timeout=timeout, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"glTF validator failed (exit {proc.returncode}): "
                           f"{proc.stderr.decode(errors='replace')}")
    return json.loads(proc.stdout)


def issue_codes(report: dict[str, Any], max_severity: int = 3) -> list[str]:
    """Codes of the report's messages with severity <= ``max_severity`` (0 = errors only)."""
    return [m["code"] for m in report["issues"]["messages"] if m["severity"] <= max_severity]
