"""Flatten whole models into atlases: ours (solver.parameterize, seams="auto") beside
xatlas's own atlas (its charting, parameterization and packing) in the same run.

Per mesh and method: charts, flipped faces (against their uv island's majority), mean
relative edge-length change and mean largest corner-angle change (uv scaled once so its
area equals the 3D area: no per-chart rescaling), packing efficiency (fraction of the
bounding square the charts cover), overlapping texels (rasterized at 2048²) and seconds.

Meshes: every mesh in ../shared/meshes, a multi-part model made of the small shared
meshes side by side, and a public collection fetched from GitHub (odedstein/meshes @
835213277571d625722d25880c9c3010c6f45a5a, ``objects/<name>/<name>.obj``, not committed:
pass the folder holding them with ``--extra``; its OBJ files are welded by
position: trimesh splits their vertices). Run from the repository root::

    PYTHONPATH=$PWD python -m bench.flatten --extra /tmp/odedstein [--only bunny.off ...]

``--ours-only --runs 2`` times our atlas alone, the least of two runs (two versions compared
from two ``git archive`` trees, one after the other). ``--alternative`` adds two chartings
with the same flattening, packer and measures: the bisection alone
(``chart_layouts(seeds="components")``, the previous seams) and xatlas's charts flattened by
our method without our checks (the alternative the issue names).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import SHARED_MESHES
from solver.chart_flattening import relative_length_change
from solver.mesh.packing import rasterized_overlap, signed_areas
from tests.helpers.meshes import side_by_side

SMALL_PARTS = ("decimated-knight.off", "torus.off", "octopus-low-surface.off", "face.off")
"""The shared meshes put side by side into the multi-part model."""


def load(path: Path, weld: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a file; ``weld``: vertices at equal positions merged (the
    public OBJ files whose faces trimesh splits on ``vt``/``vn``; the shared meshes are
    read as they are: the beetle has distinct vertices at equal positions)."""
    import trimesh

    mesh = trimesh.load(path, process=False, force="mesh")
    if weld:
        mesh.merge_vertices(merge_tex=True, merge_norm=True)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def multi_part() -> tuple[np.ndarray, np.ndarray]:
    """The :data:`SMALL_PARTS` meshes side by side (one model of 4 parts)."""
    return side_by_side(*(load(SHARED_MESHES / name) for name in SMALL_PARTS))


def measures(V: np.ndarray, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
             uv_vertex: np.ndarray) -> dict[str, Any]:
    """Flips, distortion (uv scaled to the 3D area), efficiency and overlap of an atlas."""
    from solver.mesh.metrics import corner_angles

    area3d = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                  axis=1).sum()
    low = uv.min(axis=0)
    side = float((uv.max(axis=0) - low).max())
    unit = (uv - low) / side
    signed = signed_areas(unit, uv_faces)
    scaled = unit * np.sqrt(area3d / np.abs(signed).sum())
    flat3 = np.column_stack([scaled, np.zeros(len(scaled))])
    angle = np.abs(corner_angles(flat3, uv_faces) - corner_angles(V, F)).max(axis=1)
    length = np.abs(relative_length_change(V, scaled, uv_faces, uv_vertex))
    return {"flips": flipped_faces(signed, uv_faces), "length": float(length.mean()),
            "angle": float(angle.mean()), "efficiency": float(np.abs(signed).sum()),
            "overlap": rasterized_overlap(unit, uv_faces, 2048)}


def flipped_faces(signed: np.ndarray, uv_faces: np.ndarray) -> int:
    """Faces whose orientation disagrees with the majority of their uv island (xatlas
    mirrors whole charts, v down, which is no flip)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    m, k = len(uv_faces), int(uv_faces.max()) + 1
    incidence = sp.coo_array((np.ones(3 * m), (np.repeat(np.arange(m), 3), uv_faces.ravel())),
                             shape=(m, k)).tocsr()
    _, island = connected_components(incidence @ incidence.T, directed=False)
    negative = np.bincount(island, signed < 0)
    positive = np.bincount(island, signed > 0)
    return int(np.minimum(negative, positive).sum())


def ours(V: np.ndarray, F: np.ndarray, runs: int = 1) -> dict[str, Any]:
    """solver.parameterize's atlas (seconds: the least of ``runs``)."""
    import solver

    seconds = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        result = solver.parameterize(V, F)
        seconds = min(seconds, time.perf_counter() - start)
    found = measures(V, F, result.texcoords, result.uv_faces, result.uv_vertex)
    return {"charts": result.report.atlas["charts"], **found, "seconds": seconds}


def xatlas_atlas(V: np.ndarray, F: np.ndarray) -> dict[str, Any]:
    """xatlas's own atlas (default chart and pack options)."""
    import xatlas

    start = time.perf_counter()
    atlas = xatlas.Atlas()
    atlas.add_mesh(V.astype(np.float32), F.astype(np.uint32))
    atlas.generate()
    mapping, faces, uv = atlas.get_mesh(0)
    seconds = time.perf_counter() - start
    texels = uv.astype(np.float64) * [atlas.width, atlas.height]
    found = measures(V, F, texels, faces.astype(np.int64), mapping.astype(np.int64))
    return {"charts": atlas.chart_count, **found, "seconds": seconds}


def bisection_only(V: np.ndarray, F: np.ndarray) -> dict[str, Any]:
    """The previous charting: recursive bisection from the connected components
    (solver.atlas.chart_layouts with ``seeds="components"``), same checks, same packer."""
    return _charted(V, F, "components")


def _charted(V: np.ndarray, F: np.ndarray, seeds: str) -> dict[str, Any]:
    from solver.atlas import assemble, chart_layouts
    from solver.mesh.forms import fundamental_forms
    from solver.mesh.packing import pack_charts
    from solver.mesh.topology import build_topology
    from solver.options import ParameterizeOptions
    from solver.reports import Stages

    start = time.perf_counter()
    topology = build_topology(F, n_vertices=len(V))
    angles = fundamental_forms(V, F).angles
    charts = chart_layouts(V, topology, angles, ParameterizeOptions(), Stages(None),
                           seeds=seeds)
    layout, uv_faces, uv_vertex, face_chart = assemble(charts, len(F))
    packed = pack_charts(layout, uv_faces, face_chart)
    seconds = time.perf_counter() - start
    found = measures(V, F, packed.texcoords, uv_faces, uv_vertex)
    return {"charts": len(charts), **found, "seconds": seconds}


def xatlas_charts_unchecked(V: np.ndarray, F: np.ndarray) -> dict[str, Any]:
    """xatlas's charts each flattened by our method (refined) and packed by ours, with
    none of our checks (a chart that folds or overlaps itself is kept)."""
    from solver.atlas import ChartLayout, assemble, chart_options
    from solver.chart_flattening import flatten_chart
    from solver.mesh.charts import chart_mesh, xatlas_charts
    from solver.mesh.packing import pack_charts
    from solver.mesh.topology import build_topology
    from solver.options import ParameterizeOptions
    from solver.reports import Stages

    start = time.perf_counter()
    label = xatlas_charts(V, F)
    layouts = []
    for chart in np.unique(label):                              # a loop over charts
        piece = chart_mesh(F, np.flatnonzero(label == chart))
        topology = build_topology(piece.faces, n_vertices=len(piece.vertex_ids))
        Vc = V[piece.vertex_ids]
        lengths = np.linalg.norm(Vc[topology.edges[:, 1]] - Vc[topology.edges[:, 0]], axis=1)
        opts = chart_options(ParameterizeOptions(), len(piece.face_ids))
        layouts.append(ChartLayout(piece, flatten_chart(Vc, topology, lengths, opts,
                                                        Stages(None), refine=True)))
    layout, uv_faces, uv_vertex, face_chart = assemble(layouts, len(F))
    packed = pack_charts(layout, uv_faces, face_chart)
    seconds = time.perf_counter() - start
    found = measures(V, F, packed.texcoords, uv_faces, uv_vertex)
    return {"charts": len(layouts), **found, "seconds": seconds}


def cases(extra: Path | None) -> list[tuple[str, Any]]:
    """(name, loader) of every benchmark mesh."""
    shared = sorted((p for p in SHARED_MESHES.glob("*") if p.suffix in (".obj", ".off")),
                    key=lambda p: p.stat().st_size)                # small meshes first
    found: list[tuple[str, Any]] = [(path.name, lambda p=path: load(p)) for path in shared]
    found.append(("multi-part (4 shared meshes)", multi_part))
    if extra is not None:
        found += [(f"odedstein/{path.name}", lambda p=path: load(p, weld=True))
                  for path in sorted(extra.glob("*.obj"))]
    return found


def row(name: str, faces: int, method: str, found: dict[str, Any]) -> str:
    return (f"| {name} | {faces} | {method} | {found['charts']} | {found['flips']} | "
            f"{found['length']:.4f} | {found['angle']:.4f} | {found['efficiency']:.3f} | "
            f"{found['overlap']} | {found['seconds']:.1f} |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--extra", type=Path, help="folder of the fetched public meshes")
    parser.add_argument("--only", nargs="*", help="mesh names to run")
    parser.add_argument("--alternative", action="store_true", help="also the bisection "
                        "alone and xatlas's charts flattened by ours without our checks")
    parser.add_argument("--ours-only", action="store_true",
                        help="our atlas alone (no xatlas atlas row): for timing two versions")
    parser.add_argument("--runs", type=int, default=1,
                        help="time our atlas this many times and report the least")
    args = parser.parse_args(argv)
    print("| mesh | faces | method | charts | flips | mean length change | mean angle change "
          "(rad) | packing efficiency | overlapping texels | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, loader in cases(args.extra):
        if args.only and not any(want in name for want in args.only):
            continue
        V, F = loader()
        methods: list[tuple[str, Any]] = [("ours", lambda V, F: ours(V, F, args.runs))]
        if not args.ours_only:
            methods.append(("xatlas", xatlas_atlas))
        if args.alternative:
            methods += [("bisection only", bisection_only),
                        ("xatlas charts, our flattening, no checks", xatlas_charts_unchecked)]
        for method, run in methods:
            try:
                print(row(name, len(F), method, run(V, F)), flush=True)
            except Exception as error:  # a benchmark row names the failure
                print(f"| {name} | {len(F)} | {method} | failed: {error} |||||||", flush=True)


if __name__ == "__main__":
    main()
