"""The default (refined) reconstruction below 100K faces against another commit's, in one
process: noisy forms (every dihedral angle + N(0, 1e-3) rad) and forms with the angles
scaled by 0.8, each mesh timed alternately by the working tree's solver and the baseline's
(:func:`bench.baseline.solver_at`) so that both see the same load; the ratio of the medians
is the result (issue 45: nothing regresses below 100K faces).

    python -m bench.default_ab --baseline 7e4275a
    python -m bench.default_ab --baseline HEAD~5 --meshes rocker-arm.obj --pairs 5
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import solver
from bench.baseline import solver_at
from bench.common import load_bench_mesh

MESHES = ("rocker-arm.obj", "bunny.off", "cactus.off")
"""Shared meshes of 7K-20K faces (open and closed, genus 0 and 1)."""


def _cases(names: list[str]) -> list[tuple[str, str, solver.Forms, np.ndarray]]:
    rng = np.random.default_rng(0)
    cases = []
    for name in names:
        forms = solver.fundamental_forms(*load_bench_mesh(name))
        cases.append((name, "noise", forms, forms.angles + rng.normal(0, 1e-3, len(forms.angles))))
        cases.append((name, "x0.8", forms, forms.angles * 0.8))
    return cases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", required=True, help="git revision to compare with")
    parser.add_argument("--meshes", nargs="+", default=list(MESHES))
    parser.add_argument("--pairs", type=int, default=3, help="alternate runs per case")
    args = parser.parse_args()
    old = solver_at(args.baseline)
    print("| mesh | forms | faces | baseline s | this tree s | ratio |")
    print("|---|---|---:|---:|---:|---:|")
    for name, kind, forms, angles in _cases(args.meshes):
        seconds: dict[str, list[float]] = {"old": [], "new": []}
        for _ in range(args.pairs):
            for label, module in (("old", old), ("new", solver)):
                start = time.perf_counter()
                module.reconstruct(forms.faces, forms.edges, forms.lengths, angles)
                seconds[label].append(time.perf_counter() - start)
        before, after = np.median(seconds["old"]), np.median(seconds["new"])
        print(f"| {name} | {kind} | {len(forms.faces)} | {before:.2f} | {after:.2f} | "
              f"{after / before:.3f} |", flush=True)


if __name__ == "__main__":
    main()
