"""Per-drag cost of the linear ``Deformer.solve`` against references measured in the same run.

Guards the regression of issue 19: a PARDISO factor given a user permutation (``iparm[4]``
1 or 2: the ordering hint, or asking PARDISO to return its ordering for the analysis cache)
is a classic one-level factor, not the two-level one ``iparm[23] = 1`` asks for, and its
back-substitution costs 1.3-1.5x more. The ``Deformer`` factorizes without a hint since
then. On one ~20K-face mesh this script builds the ``Deformer`` (cold analysis cache) and
times, interleaved over several rounds in this process:

* ``Deformer.solve`` (linear, defaults) per drag, median of the round's drags;
* the Deformer's own factor: one solve of 3 right-hand sides (what a drag back-substitutes);
* the same matrix factorized by PARDISO with the ordering hint (the regressed setting);
* the same matrix factorized by SciPy's SuperLU (the project's ``"superlu"`` backend): a
  reference that no PARDISO setting changes.

A regression shows as ``Deformer.solve`` / SuperLU going up, and as the Deformer's factor no
longer beating the hinted one (its ratio to it back near 1). Set-up seconds (analysis +
numerical factorization) of each factor are printed too: the hint's cheaper analysis is
what the drags give up.

    python -m bench.drag_regression [icosphere | MESH in ../shared/meshes] [--rounds 5]
    MKL_NUM_THREADS=1 python -m bench.drag_regression     # one MKL thread
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import numpy as np

from bench.common import load_bench_mesh, random_drags, two_handle_regions
from solver import Deformer, linalg
from solver.linear.system import unknown_groups

DRAGS = 15  # per round, as in the bisection


def median_ms(action: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``action`` over ``repeats`` calls, in milliseconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def spread(ratios: np.ndarray) -> str:
    """``median (min-max)`` of per-round ratios."""
    return f"{np.median(ratios):.2f} ({ratios.min():.2f}-{ratios.max():.2f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", nargs="?", default="icosphere")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    V, F = load_bench_mesh(args.mesh)
    handles = two_handle_regions(V)
    moves = random_drags(V, handles, DRAGS + 1)

    linalg.clear_analysis_cache()
    start = time.perf_counter()
    deformer = Deformer(V, F, handles, backend="pardiso")
    deformer_setup = time.perf_counter() - start
    deformer.solve(moves[0])  # the first solve verifies the factor
    own = deformer.system.factor
    K = own._matrix  # the factorized matrix (private: the benchmark needs the same one)
    topology = deformer.problem.topology
    groups = unknown_groups(topology.n_vertices, topology.n_faces)
    linalg.clear_analysis_cache()  # cold analyses for the references too
    hinted = linalg.factorize(K, "pardiso", assume_symmetric=True, groups=groups)
    superlu = linalg.factorize(K, "superlu", assume_symmetric=True)
    rhs = np.random.default_rng(1).normal(size=(K.shape[0], 3))
    factors = {"Deformer's factor": own, "PARDISO, ordering hint": hinted,
               "SuperLU": superlu}
    for factor in factors.values():
        factor.solve(rhs)  # verified once: later solves only back-substitute

    rows: dict[str, list[float]] = {"Deformer.solve (per drag)": []}
    rows.update({f"{name}: solve, 3 rhs": [] for name in factors})
    for _ in range(args.rounds):
        targets = iter(moves[1:])
        rows["Deformer.solve (per drag)"].append(
            median_ms(lambda t=targets: deformer.solve(next(t)), DRAGS))
        for name, factor in factors.items():
            rows[f"{name}: solve, 3 rhs"].append(median_ms(lambda f=factor: f.solve(rhs),
                                                           DRAGS))

    superlu_ms = np.array(rows["SuperLU: solve, 3 rhs"])
    hinted_ms = np.array(rows["PARDISO, ordering hint: solve, 3 rhs"])
    threads = os.environ.get("MKL_NUM_THREADS", "default")
    print(f"{args.mesh}: {len(V)} vertices, {len(F)} faces, {K.shape[0]} unknowns, "
          f"{len(handles)} handle vertices; MKL threads {threads}; {args.rounds} rounds of "
          f"{DRAGS}; load {os.getloadavg()[0]:.1f}")
    print("\n| what | ms, median of rounds (range) | / SuperLU solve, same round "
          "| / hinted PARDISO solve, same round |")
    print("|---|---|---|---|")
    for name, values in rows.items():
        v = np.array(values)
        print(f"| {name} | {np.median(v):.1f} ({v.min():.1f}-{v.max():.1f}) | "
              f"{spread(v / superlu_ms)} | {spread(v / hinted_ms)} |")
    print("\n| factor | set-up s (analysis + factorization) |")
    print("|---|---|")
    print(f"| Deformer (whole constructor, cold) | {deformer_setup:.2f} |")
    for name, factor in factors.items():
        if name != "Deformer's factor":
            print(f"| {name} | {sum(factor.timings.values()):.2f} |")
    print(f"| Deformer's factor (PARDISO, no hint) | {sum(own.timings.values()):.2f} |")


if __name__ == "__main__":
    main()
