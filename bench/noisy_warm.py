"""Warm linear reconstruct of noisy forms (angles + N(0, 1e-3), ``refine=False``): min and
median of 5 calls after one warm-up, in this process. Run it in two trees alternately to
compare them (bench/README.md, "Noisy forms no longer build the tree integration"):

    python -m bench.noisy_warm rocker-arm.obj
"""

from __future__ import annotations

import sys
import time

import numpy as np

import solver
from bench.common import SHARED_MESHES
from solver.mesh.io import load_mesh_file


def main(name: str) -> None:
    V, F = load_mesh_file(SHARED_MESHES / name)
    forms = solver.fundamental_forms(V, F)
    angles = forms.angles + np.random.default_rng(0).normal(0, 1e-3, len(forms.angles))

    def call() -> solver.Reconstruction:
        return solver.reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                                  refine=False)

    call()
    times = []
    for _ in range(5):
        start = time.perf_counter()
        result = call()
        times.append(time.perf_counter() - start)
    print(f"{name}: min {min(times):.3f} s, median {np.median(times):.3f} s, "
          f"{result.report['solve_path']}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "rocker-arm.obj")
