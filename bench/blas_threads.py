"""Why the refinement runs numpy's BLAS on one thread: the cost of its dot products.

The refinement's vectors have tens of thousands of entries (3 x the free vertices). numpy's
``dot`` hands them to a multithreaded BLAS, whose threads pay off only for far longer
vectors; on a loaded machine their start-up dominates. This times ``rounds`` batches of
8 dot products of ``size`` entries (the L-BFGS recursion of one step does 16), three ways:
numpy's default BLAS threads, BLAS limited to one thread (``threadpoolctl``, as
:meth:`solver.refine.Refiner.run` does) and ``einsum`` (no BLAS). Medians in milliseconds;
run it on a quiet machine and under load (beside the test suite, or beside six busy
processes: ``for i in 1 2 3 4 5 6; do timeout 25 python -c "while True: pass" & done``)
and compare.

    python -m bench.blas_threads [--size 30000] [--rounds 20]
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
from threadpoolctl import ThreadpoolController

from bench.common import load_averages


def batch_ms(dot, vectors: list[np.ndarray]) -> float:
    """Milliseconds of 8 dot products with ``dot`` over ``vectors``."""
    start = time.perf_counter()
    for a, b in itertools.pairwise(vectors):  # 9 vectors: 8 products
        float(dot(a, b))
    return 1000 * (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=30000)
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    vectors = list(np.random.default_rng(0).standard_normal((9, args.size)))
    controller = ThreadpoolController()
    threads = [info["num_threads"] for info in controller.info() if info["user_api"] == "blas"]
    ways = {"numpy dot, default BLAS threads": lambda: batch_ms(np.dot, vectors),
            "numpy dot, BLAS on one thread": None,
            "einsum": lambda: batch_ms(lambda a, b: np.einsum("i,i->", a, b), vectors)}
    times: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(args.rounds):  # alternating, so that load changes hit all three alike
        for name, run in ways.items():
            if run is None:
                with controller.limit(limits=1, user_api="blas"):
                    times[name].append(batch_ms(np.dot, vectors))
            else:
                times[name].append(run())
    print(f"load {load_averages()}; BLAS threads by default {threads}; "
          f"8 dot products of {args.size} entries, median of {args.rounds} rounds\n")
    print("| way | ms |")
    print("|---|---|")
    for name, values in times.items():
        print(f"| {name} | {np.median(values):.3f} |")


if __name__ == "__main__":
    main()
