"""The packages' import boundaries, read from the sources (every ``import`` statement,
including the ones inside functions): the client (``ffs``) and the service (``service``)
never import each other, they share only ``ffs_wire``; the library (``solver``) imports
neither; ``ffs_wire`` imports numpy and the standard library only; and ``import ffs.client``
loads neither FastAPI nor the library."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def imported_roots(package: str) -> dict[str, set[str]]:
    """Top-level package of every import in ``package``'s sources -> the files importing it."""
    roots: dict[str, set[str]] = {}
    for path in sorted((REPO / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                roots.setdefault(name.split(".")[0], set()).add(str(path.relative_to(REPO)))
    return roots


@pytest.mark.parametrize(("package", "forbidden"), [
    ("ffs", {"service"}),
    ("service", {"ffs"}),
    ("solver", {"service", "ffs", "ffs_wire"}),
])
def test_no_import_across_the_boundary(package, forbidden):
    roots = imported_roots(package)
    crossing = {root: sorted(roots[root]) for root in forbidden & roots.keys()}
    assert not crossing, f"{package} imports {crossing}"


def test_the_wire_format_needs_only_numpy():
    roots = set(imported_roots("ffs_wire")) - {"__future__", "numpy"}
    assert roots <= set(sys.stdlib_module_names), roots - set(sys.stdlib_module_names)
    # and both sides do use it (the one place the format is defined)
    for package in ("ffs", "service"):
        assert "ffs_wire" in imported_roots(package), package


def test_importing_the_client_loads_neither_fastapi_nor_the_library():
    code = ("import sys, ffs.client, ffs.operations, ffs.sessions\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'fastapi', 'starlette', 'uvicorn', 'pydantic', 'service', 'solver', 'scipy', "
            "'trimesh'}))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
