"""Every mesh file of a folder through every operation, one row per file (issue 40).

For each OBJ, OFF, PLY, STL, GLB file of DIR (sorted by name; ``--max-faces`` skips larger
ones, ``--recursive`` descends) the library is run as ``ffs`` runs it, in the file's vertex
numbering:

* ``forms``: :func:`solver.mesh.io.read_mesh` (polygons triangulated) then
  :func:`solver.fundamental_forms` (a non-manifold mesh's cut; parts' placement).
* ``exact``: :func:`solver.reconstruct` of those forms (vertex map, weld map and
  placement; "welded / dropped": vertices joined by zero-length edges, faces dropped); the
  whole-mesh error after one rigid alignment, in units of the bounding-box diagonal.
* ``noisy``: the same with N(0, 1e-3) rad on every interior dihedral angle (seed 0): the
  whole-mesh error, whether the refinement converged, its iterations and factorizations,
  and its time against the linear answer's (``refine=False``, timed first).
* ``deform``: three vertices (seed 0) moved by 5% of the diagonal: the largest handle miss.
* ``flatten``: :func:`solver.parameterize`: ok, or the problem kind (closed surfaces are
  refused until issue 41's seams).

A failure is the error's kind (``non-manifold-edge``, ``degenerate-face``, ...), never a
traceback; the table ends with the score per operation.

    python -m bench.corpus ../shared/meshes [--max-faces 120000] [--skip-flatten]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import solver
from solver.core.errors import SolverInputError
from solver.mesh.io import LOAD_FORMATS, file_bytes, read_mesh
from solver.mesh.topology import build_topology

NOISE = 1e-3
"""Dihedral noise of the noisy round trip, radians."""
HANDLE_SHIFT = 0.05
"""Handle displacement of the deform case, fraction of the diagonal."""


@dataclass
class Row:
    """One file's results."""

    name: str
    faces: int = 0
    outcome: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    values: dict[str, Any] = field(default_factory=dict)


def rigid_error(X: np.ndarray, Y: np.ndarray) -> float:
    """Max vertex distance after the best rotation + translation, over Y's diagonal."""
    Xc, Yc = X - X.mean(axis=0), Y - Y.mean(axis=0)
    U, _, Vt = np.linalg.svd(Xc.T @ Yc)
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ np.diag([1.0, 1.0, d]) @ Vt
    return float(np.abs(Xc @ R - Yc).max() / np.linalg.norm(Y.max(axis=0) - Y.min(axis=0)))


def _kind(exc: BaseException) -> str:
    return getattr(exc, "kind", type(exc).__name__)


def _timed(row: Row, stage: str, run: Any) -> Any:
    """``run()``, its time and outcome in ``row``; None when it raised."""
    start = time.perf_counter()
    try:
        result = run()
    except (SolverInputError, ArithmeticError, ValueError, MemoryError) as exc:
        row.outcome[stage] = _kind(exc)
        row.seconds[stage] = time.perf_counter() - start
        return None
    row.seconds[stage] = time.perf_counter() - start
    row.outcome[stage] = "ok"
    return result


def _reconstruct(forms: solver.Forms, angles: np.ndarray, n: int, **options: Any
                 ) -> solver.Reconstruction:
    return solver.reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                              vertex_map=forms.vertex_map, placement=forms.placement,
                              weld_map=forms.weld_map, n_vertices=n, **options)


def run_file(path: Path, skip_flatten: bool = False) -> Row:
    """Every operation on one file."""
    row = Row(path.name)
    loaded = _timed(row, "read", lambda: read_mesh(file_bytes(path), path.name))
    if loaded is None:
        return row
    V, F = loaded.vertices, loaded.faces
    row.faces = len(F)
    forms = _timed(row, "forms", lambda: solver.fundamental_forms(V, F))
    if forms is None:
        return row
    kept = F if forms.dropped_faces is None else np.delete(F, forms.dropped_faces, axis=0)
    used = np.unique(kept)  # the vertices the forms place (not those of dropped faces only)
    row.values["cut"] = (0 if forms.vertex_map is None
                         else len(forms.vertex_map) - len(V))
    row.values["parts"] = len(forms.placement.faces)
    row.values["welded"] = (0 if forms.weld_map is None
                            else int((forms.weld_map != np.arange(len(V))).sum()))
    row.values["dropped"] = 0 if forms.dropped_faces is None else len(forms.dropped_faces)
    exact = _timed(row, "exact", lambda: _reconstruct(forms, forms.angles, len(V)))
    if exact is not None:
        row.values["exact_error"] = rigid_error(exact.vertices[used], V[used])
    inner = build_topology(forms.faces).interior_edges
    angles = forms.angles.copy()
    angles[inner] += np.random.default_rng(0).normal(0, NOISE, len(inner))
    linear = _timed(row, "linear", lambda: _reconstruct(forms, angles, len(V), refine=False))
    noisy = _timed(row, "noisy", lambda: _reconstruct(forms, angles, len(V)))
    if noisy is not None:
        refinement = noisy.report["refinement"]
        row.values["noisy_error"] = rigid_error(noisy.vertices[used], V[used])
        row.values["converged"] = bool(refinement.get("converged", not refinement["refined"]))
        row.values["iterations"] = refinement.get("iterations", 0)
        row.values["factorizations"] = refinement.get("factorizations", 0)
        if linear is not None:
            row.values["x_linear"] = row.seconds["noisy"] / max(row.seconds["linear"], 1e-9)
    rng = np.random.default_rng(0)
    groups = used if forms.weld_map is None else np.unique(forms.weld_map[used])
    handles = rng.choice(groups, min(3, len(groups)), replace=False)  # one per welded vertex
    diagonal = float(np.linalg.norm(V[used].max(axis=0) - V[used].min(axis=0)))
    targets = V[handles] + rng.normal(0, HANDLE_SHIFT * diagonal, (len(handles), 3))
    moved = _timed(row, "deform", lambda: solver.deform(V, F, handles, targets))
    if moved is not None:
        row.values["handle_miss"] = float(np.abs(moved.vertices[handles] - targets).max()
                                          / diagonal)
    if not skip_flatten:
        _timed(row, "flatten", lambda: solver.parameterize(V, F))
    return row


def mesh_files(folder: Path, recursive: bool, max_faces: int | None) -> list[Path]:
    """The mesh files of ``folder`` by name (those of :data:`solver.mesh.io.LOAD_FORMATS`)."""
    pattern = "**/*" if recursive else "*"
    found = [p for p in folder.glob(pattern)
             if p.is_file() and p.suffix.lower().lstrip(".") in LOAD_FORMATS]
    del max_faces  # applied after reading (a header's count is not every format's)
    return sorted(found)


def _cell(row: Row, stage: str, value: str = "") -> str:
    outcome = row.outcome.get(stage, "-")
    return value if outcome == "ok" and value else outcome


def print_table(rows: list[Row]) -> None:
    """The markdown table and the score per operation."""
    print("| file | faces | cut vertices | welded / dropped | parts | forms | exact error | "
          "noisy error | converged | iterations / factorizations | noisy s (x linear) | "
          "deform miss | flatten |")
    print("|---|---:|---:|---:|---:|---|---:|---:|---|---:|---:|---:|---|")
    for r in rows:
        v = r.values
        noisy = (f"{r.seconds['noisy']:.2f} ({v['x_linear']:.1f}x)" if "x_linear" in v
                 else _cell(r, "noisy"))
        forms_s = f"{r.seconds.get('forms', 0):.2f} s"
        exact = f"{v.get('exact_error', 0):.1e}"
        noisy_error = f"{v.get('noisy_error', 0):.1e}"
        miss = f"{v.get('handle_miss', 0):.1e}"
        welded = (f"{v['welded']} / {v['dropped']}" if "welded" in v else "-")
        print(f"| {r.name} | {r.faces} | {v.get('cut', '-')} | {welded} | "
              f"{v.get('parts', '-')} | "
              f"{_cell(r, 'forms', forms_s) if r.outcome['read'] == 'ok' else r.outcome['read']}"
              f" | {_cell(r, 'exact', exact)} | "
              f"{_cell(r, 'noisy', noisy_error)} | {v.get('converged', '-')} | "
              f"{v.get('iterations', '-')} / {v.get('factorizations', '-')} | {noisy} | "
              f"{_cell(r, 'deform', miss)} | {r.outcome.get('flatten', '-')} |")
    total = len(rows)
    for stage in ("forms", "exact", "noisy", "deform", "flatten"):
        ok = sum(r.outcome.get(stage) == "ok" for r in rows)
        print(f"\n{stage}: {ok}/{total}", end="")
    print()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--max-faces", type=int, default=None,
                        help="skip files with more faces (after triangulation)")
    parser.add_argument("--recursive", action="store_true")
    parser.add_argument("--skip-flatten", action="store_true")
    args = parser.parse_args(argv)
    rows = []
    for path in mesh_files(args.folder, args.recursive, args.max_faces):
        if args.max_faces is not None:
            try:
                faces = len(read_mesh(path.read_bytes(), path.name).faces)
            except SolverInputError:
                faces = 0
            if faces > args.max_faces:
                print(f"skipped {path.name}: {faces} faces", file=sys.stderr)
                continue
        started = time.perf_counter()
        rows.append(run_file(path, args.skip_flatten))
        print(f"{path.name}: {time.perf_counter() - started:.1f} s {rows[-1].outcome}",
              file=sys.stderr, flush=True)
    print_table(rows)


if __name__ == "__main__":
    main()
