"""The solver's layers: no module imports from a layer above its own.

Every import counts, at module level or inside a function, relative or absolute. The layers
are declared here, bottom first; a module of ``solver/`` that no layer names is an entry
point (the top layer). That the solver imports neither the service nor the client is
``tests/test_package_boundaries.py``'s.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

LAYERS: dict[str, int] = {
    "solver.core": 0,     # errors, serialization, validation, budgets, warnings
    "solver.linalg": 1,   # sparse factorizations
    "solver.mesh": 2,     # topology, forms, frames, geometry, files, charts
    "solver.linear": 3,   # Eq. (5): system, constraints, integrability, layout fit
    "solver.refine": 3,   # the nearest surface: energies, steps, stopping, Refiner
}
"""Package -> rank. A module may import its own package and packages of lower rank only
(``linear`` and ``refine`` share a rank: neither imports the other)."""
TOP = 4
"""The rank of the entry points (reconstruct, deform, parameterize, ...) and ``solver``."""


def layer_of(module: str) -> tuple[str, int]:
    """The layer package and rank of a dotted module name of the solver."""
    for package, rank in LAYERS.items():
        if module == package or module.startswith(package + "."):
            return package, rank
    return "solver", TOP


def module_name(path: Path) -> tuple[str, bool]:
    """The dotted name of ``path`` (relative to the repository) and whether it is a
    package's ``__init__``."""
    parts = list(path.with_suffix("").parts)
    package = parts[-1] == "__init__"
    return ".".join(parts[:-1] if package else parts), package


def imports(source: str, module: str, package: bool) -> list[tuple[int, str]]:
    """Every module ``source`` (of ``module``) imports, as (line, dotted name); relative
    imports resolved; ``from X import name`` counts as ``X.name`` (it may be a module)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".") if package else module.split(".")[:-1]
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def violations(source: str, module: str, package: bool = False) -> list[str]:
    """The imports of ``source`` that break the layering, in words."""
    own, rank = layer_of(module)
    bad = []
    for line, target in imports(source, module, package):
        if target.split(".")[0] != "solver":
            continue
        theirs, their_rank = layer_of(target)
        if theirs != own and their_rank >= rank and not (theirs == "solver" and rank == TOP):
            bad.append(f"{module}:{line} ({own}) imports {target} ({theirs}): not below")
    return bad


SOLVER_FILES = sorted((REPO / "solver").rglob("*.py"))


def test_the_layers_cover_every_package_of_the_solver():
    packages = {module_name(p.relative_to(REPO))[0] for p in SOLVER_FILES
                if p.name == "__init__.py"}
    assert packages - {"solver"} == set(LAYERS), packages


@pytest.mark.parametrize("path", SOLVER_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_no_upward_import(path):
    module, package = module_name(path.relative_to(REPO))
    assert violations(path.read_text(encoding="utf-8"), module, package) == []


def test_the_check_sees_an_upward_import_a_lazy_one_and_a_sibling():
    """The checker itself: a mesh module importing the refinement (relatively, inside a
    function) and the refinement importing the linear layer are caught; downward imports
    are not."""
    upward = "def f():\n    from ..refine.form_energy import FormTargets\n"
    assert violations(upward, "solver.mesh.topology") == [
        "solver.mesh.topology:2 (solver.mesh) imports solver.refine.form_energy.FormTargets "
        "(solver.refine): not below"]
    sibling = "from solver.linear.system import energies\n"
    assert len(violations(sibling, "solver.refine.refiner")) == 1
    assert violations("from ..core.errors import SolverInputError\n",
                      "solver.mesh.topology") == []
    assert violations("from .refine import Refiner\n", "solver.deform") == []
