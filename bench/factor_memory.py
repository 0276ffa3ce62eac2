"""What keeping idle PARDISO handles' factor memory saves, measured in one run.

A dead factorization's PARDISO handle goes back to ``solver.linalg``'s analysis cache. It
keeps its factor's memory there (``kept``, the default), or, as before session 4, frees the
factor when parked (``dropped``: every refactorization of the pattern maps and faults its
factor in again). For each mode, in a fresh process: one refined reconstruct of noisy forms
to warm up, then ``--repeats`` more, each measured by minor page faults, system and user CPU
time and wall time (``getrusage``); modes alternate. Also prints the analysis cache's
counters after the first reconstruct (``cached_ordering`` 0: the orthonormalization reused
the linear solve's analysis instead of redoing the symbolic phase).

    python -m bench.factor_memory [mesh] [--repeats 3] [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

from bench.common import REPO, load_bench_mesh


def measure(mesh: str, mode: str, repeats: int) -> dict:
    import numpy as np

    from solver import fundamental_forms, linalg, reconstruct
    from solver.linalg import analysis_cache

    if mode == "dropped":  # the old parking: free the factor, keep the analysis
        park = analysis_cache.AnalysisCache.park

        def park_dropping(self, key, handle):  # type: ignore[no-untyped-def]
            handle.drop_factor()
            park(self, key, handle)

        analysis_cache.AnalysisCache.park = park_dropping
    V, F = load_bench_mesh(mesh)
    forms = fundamental_forms(V, F)
    angles = forms.angles.copy()
    inner = angles != 0
    angles[inner] += np.random.default_rng(0).normal(scale=1e-3, size=int(inner.sum()))

    def run() -> dict:
        return reconstruct(forms.faces, forms.edges, forms.lengths, angles,
                           n_vertices=len(V)).report

    run()
    counters = linalg.analysis_cache_info()
    rows = []
    for _ in range(repeats):
        before, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        report = run()
        after = resource.getrusage(resource.RUSAGE_SELF)
        rows.append({"wall": time.perf_counter() - start,
                     "faults": after.ru_minflt - before.ru_minflt,
                     "sys": after.ru_stime - before.ru_stime,
                     "user": after.ru_utime - before.ru_utime,
                     "factorizations": report["refinement"].get("factorizations")})
    return {"mode": mode, "rows": rows, "counters": counters, "load": os.getloadavg()[0]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", nargs="?", default="rocker-arm.obj")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--mode", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.mode:
        print(json.dumps(measure(args.mesh, args.mode, args.repeats)))
        return
    print(f"{args.mesh}: refined reconstruct of noisy forms (N(0, 1e-3) rad), per call, "
          f"median of {args.repeats}\n")
    print("| round | mode | load | minor faults | sys s | user s | wall s | refinement "
          "factorizations |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|")
    counters = None
    for r in range(args.rounds):
        for mode in ("dropped", "kept"):
            out = subprocess.run([sys.executable, "-m", "bench.factor_memory", args.mesh,
                                  "--mode", mode, "--repeats", str(args.repeats)],
                                 capture_output=True, text=True, check=True, cwd=REPO)
            d = json.loads(out.stdout.strip().splitlines()[-1])
            med = {k: sorted(row[k] for row in d["rows"])[len(d["rows"]) // 2]
                   for k in ("faults", "sys", "user", "wall")}
            print(f"| {r} | {mode} | {d['load']:.1f} | {med['faults']} | {med['sys']:.2f} | "
                  f"{med['user']:.2f} | {med['wall']:.2f} | {d['rows'][0]['factorizations']} |")
            counters = d["counters"] if mode == "kept" else counters
    print(f"\nanalysis cache after the first refined reconstruct (kept): {counters}")


if __name__ == "__main__":
    main()
