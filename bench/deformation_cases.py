"""Botsch-Sorkine 2008 deformation cases (the paper's Fig. 3) with distortion measurements.

Runs bumpy-plane, cylinder, bar and cactus from ../shared/meshes with their original
selections (.sel) and handle transforms (.def): translation-only handles and handles that
also rotate the handle faces' frames, each with and without the orthonormalization solve
(Sec. 4), for each energy weighting. Prints a markdown table of edge-length change
(relative) and dihedral-angle change (radians) and writes pseudo-colour renderings to
bench/out/ (git-ignored).

    python -m bench.deformation_cases [--cases bar cylinder] [--weightings uniform]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.common import REPO, SHARED_MESHES
from solver import deform
from solver.mesh.metrics import distortion
from tests.helpers.botsch_sorkine import DeformationCase, load_case

OUT = REPO / "bench" / "out"
CASES = ("bumpy-plane", "cylinder", "bar", "cactus")


def run(case: DeformationCase, rotations: bool, orthonormalize: bool,
        weighting: str) -> tuple[np.ndarray, dict, float]:
    groups = [case.handle_faces()] if rotations else None
    rots = case.transform[None, :3, :3] if rotations else None
    t0 = time.perf_counter()
    result = deform(case.vertices, case.faces, case.handles, case.handle_targets(),
                    rotation_handles=groups, handle_rotations=rots, roi=case.roi,
                    orthonormalize=orthonormalize, weighting=weighting)
    seconds = time.perf_counter() - t0
    return result.vertices, distortion(case.vertices, result.vertices, case.faces), seconds


def render(case: DeformationCase, vertices: np.ndarray, report: dict, title: str,
           path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(10, 4.5))
    for k, (key, label) in enumerate([("length_change", "edge length change (rel.)"),
                                      ("angle_change", "dihedral change (rad)")]):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        values = np.abs(report[key])
        per_face = np.zeros(len(case.faces))
        # Face colour: mean |change| of its three edges.
        from solver.mesh.forms import fundamental_forms
        edges = fundamental_forms(case.vertices, case.faces).edges
        lookup = {tuple(e): i for i, e in enumerate(edges.tolist())}
        idx = np.array([[lookup[tuple(sorted((f[a], f[(a + 1) % 3])))] for a in range(3)]
                        for f in case.faces.tolist()])
        per_face = values[idx].mean(axis=1)
        top = max(np.percentile(values, 99), 1e-12)
        colors = plt.cm.inferno(np.clip(per_face / top, 0, 1))
        poly = Poly3DCollection(vertices[case.faces], facecolors=colors, linewidths=0)
        ax.add_collection3d(poly)
        lo, hi = vertices.min(0), vertices.max(0)
        centre, half = (lo + hi) / 2, (hi - lo).max() / 2
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_axis_off()
        ax.set_title(f"{label}\n(colour scale 0..{top:.3g})", fontsize=8)
    ax = fig.add_subplot(1, 3, 3)
    ax.hist(np.abs(report["length_change"]), bins=40, alpha=0.6, label="|length change|")
    ax.hist(np.abs(report["angle_change"]), bins=40, alpha=0.6, label="|dihedral change|")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--weightings", nargs="*", default=["uniform", "cotan_clamped",
                                                            "cotan"])
    parser.add_argument("--no-render", action="store_true")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    print("| case | faces | handles | orthonormalize | weighting | length change mean / max "
          "| dihedral change mean / max (rad) | handle error | seconds |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.cases:
        case = load_case(SHARED_MESHES, name)
        for rotations in (False, True):
            for orthonormalize in (False, True):
                for weighting in args.weightings:
                    try:
                        out, rep, sec = run(case, rotations, orthonormalize, weighting)
                    except Exception as exc:
                        print(f"| {name} | {len(case.faces)} | "
                              f"{'rotate' if rotations else 'translate'} | {orthonormalize} "
                              f"| {weighting} | failed: {type(exc).__name__}: {exc} | | | |")
                        continue
                    err = np.abs(out[case.handles] - case.handle_targets()).max()
                    ls, an = rep["length_summary"], rep["angle_summary"]
                    handles = "positions + rotation" if rotations else "positions only"
                    print(f"| {name} | {len(case.faces)} | {handles} | {orthonormalize} | "
                          f"{weighting} | {ls['mean']:.4f} / {ls['max']:.3f} | "
                          f"{an['mean']:.4f} / {an['max']:.3f} | {err:.1e} | {sec:.2f} |",
                          flush=True)
                    if not args.no_render and weighting == "uniform":
                        tag = f"{name}-{'rot' if rotations else 'pos'}-" \
                              f"{'orth' if orthonormalize else 'lin'}"
                        render(case, out, rep, f"{name}: {handles}, orthonormalize="
                               f"{orthonormalize}", OUT / f"{tag}.png")


if __name__ == "__main__":
    main()
