"""The refinement's Gauss-Newton solves by CG: capture them, then measure preconditioners,
hierarchy reuse and the setup's price on them.

The default answer of noisy forms by the iterative path (``solver.reconstruct(...,
linear_solver="iterative")``) refines by Gauss-Newton steps whose damped matrices CG solves,
preconditioned by a smoothed-aggregation hierarchy (:mod:`solver.refine.iterative_steps`).
A SOURCE is a ``bench.scale`` level (``0``: nefertiti, 99 938 faces; ``1``: 399 752) or
``MESH[:LEVEL]``, a shared mesh subdivided LEVEL times (``rocker-arm.obj``), with
``bench.scale``'s noisy forms (1e-3 rad, cached under ``/tmp/ffs-scale``). Commands:

* ``capture SOURCE...``: the default answer by the iterative path, keeping every Gauss-Newton
  solve (upper-triangle CSR matrix, free positions, rigid-motion projection, right-hand side,
  forcing term, iterations, whether the hierarchy was set up for it) under ``--captures``
  (default ``/tmp/ffs-gauss-newton``, never in git), through
  :func:`solver.refine.iterative_steps.observe_solves`.
* ``variants SOURCE...``: hierarchies of one captured matrix (``--solve``, default the last,
  the confirming solve to 1e-3) built by :class:`~solver.refine.iterative_steps.Multigrid`
  with :class:`~solver.refine.iterative_steps.HierarchyRules` that differ from the
  refinement's (:data:`~solver.refine.iterative_steps.HIERARCHY_RULES`, the ``production``
  row) in one field each; each solved by the refinement's own CG
  (:class:`~solver.refine.iterative_steps.IterativeOperator`: projected, from zero) to
  ``--tolerance`` (1e-3): levels, operator complexity, setup CPU s, CG iterations and CPU s.
* ``policies SOURCE...``: the whole default answer with the hierarchy set up again by the
  refinement's rule (``rule``), before every solve (``always``) or never after the first
  (``never``, not even after a capped solve): CPU s, CG iterations per step, setups, E;
  ``--hierarchies`` runs it with other ``variants`` (e.g. ``"energy 4"``) too.
* ``setup-price SOURCE...``: the production setup's CPU time over one CG iteration's
  (median of ``--repeats``), what ``StepRules.cg_setup_iterations`` prices a setup at.

Every measurement runs in a fresh child process (``--max-gb``: its address-space limit);
the parent prints one JSON line per row, the load and the commit, and with ``--markdown``
the tables of bench/README.md. Usage (from the repository root)::

    python -m bench.gauss_newton_cg capture 0
    python -m bench.gauss_newton_cg variants 0 --markdown
    python -m bench.gauss_newton_cg policies 0 --markdown
    python -m bench.gauss_newton_cg setup-price 0 1 --markdown
    flock /tmp/ffs-big.lock python -m bench.gauss_newton_cg variants 1 --markdown

``variants`` and ``setup-price`` capture first where the SOURCE has no capture yet.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import resource
import statistics
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from bench.common import REPO, load_averages, markdown_table
from bench.scale import BASE, forms_file
from solver.refine.iterative_steps import (
    HIERARCHY_RULES,
    GaussNewtonSolve,
    HierarchyRules,
    Multigrid,
    observe_solves,
)
from solver.refine.steps import DEFAULT_STEP_RULES

CAPTURES = Path(os.environ.get("FFS_GN_CAPTURES", "/tmp/ffs-gauss-newton"))
"""Where captured solves are kept, one folder per SOURCE (outside the repository)."""
POLICIES = ("rule", "always", "never")
TWO_SWEEPS = ("block_gauss_seidel", {"sweep": "symmetric", "iterations": 2})


def variants() -> dict[str, HierarchyRules]:
    """The hierarchies ``variants`` measures, by name: the refinement's (``production``)
    and one-field changes of it (prolongator smoothing iterations 2/4/8/16 where they are
    not the production's, a W-cycle, two Gauss-Seidel sweeps, Jacobi prolongators, per vertex
    instead of scalar unknowns, the other precision) and both (per vertex in double
    precision)."""
    prod = HIERARCHY_RULES
    kind, options = prod.smooth
    out = {"production": prod}
    for maxiter in (2, 4, 8, 16):
        rules = dataclasses.replace(prod, smooth=("energy", {**options, "maxiter": maxiter})
                                    if kind == "energy" else ("energy", {"maxiter": maxiter}))
        if rules != prod:
            out[f"energy {maxiter}"] = rules
    out["W-cycle"] = dataclasses.replace(prod, cycle="W")
    out["2 Gauss-Seidel sweeps"] = dataclasses.replace(prod, presmoother=TWO_SWEEPS,
                                                       postsmoother=TWO_SWEEPS)
    out["Jacobi prolongators"] = dataclasses.replace(prod, smooth=("jacobi", {"omega": 4 / 3}))
    out["per vertex"] = dataclasses.replace(prod, by_vertex=not prod.by_vertex)
    other = "float32" if prod.dtype == "float64" else "float64"
    out[other] = dataclasses.replace(prod, dtype=other)
    out["per vertex float64"] = dataclasses.replace(prod, by_vertex=True, dtype="float64")
    return out


def source_forms(source: str) -> tuple[str, Path]:
    """(the SOURCE's name for folders, its cached noisy forms): ``"1"`` is nefertiti's
    level 1, ``"rocker-arm.obj"`` rocker-arm's level 0, ``"bunny.obj:1"`` bunny's level 1."""
    base, _, level = source.rpartition(":") if ":" in source else ("", "", source)
    if not level.isdigit():
        base, level = source, "0"
    base = base or BASE
    return f"{Path(base).stem}-s{level}", forms_file(int(level), base)


def capture_folder(source: str, root: Path = CAPTURES) -> Path:
    """The folder of ``source``'s captured solves."""
    return root / source_forms(source)[0]


# -- capture ----------------------------------------------------------------------------

def capture(source: str, root: Path = CAPTURES) -> dict[str, Any]:
    """Run ``source``'s default answer by the iterative path in this process, saving every
    Gauss-Newton solve to ``capture_folder(source, root)`` (``solve<k>.npz`` and
    ``solve<k>-projection.pkl``) and a ``summary.json``; returns the summary."""
    from solver import reconstruct

    folder = capture_folder(source, root)
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("solve*"):
        old.unlink()
    data = np.load(source_forms(source)[1])
    solves: list[dict[str, Any]] = []

    def keep(solve: GaussNewtonSolve) -> None:
        k = len(solves)
        U = sp.csr_matrix(solve.matrix)
        np.savez(folder / f"solve{k}.npz", data=U.data, indices=U.indices, indptr=U.indptr,
                 shape=np.array(U.shape), positions=solve.positions, rhs=solve.rhs,
                 tolerance=solve.tolerance)
        with open(folder / f"solve{k}-projection.pkl", "wb") as fh:
            pickle.dump(solve.project, fh)
        solves.append({"tolerance": solve.tolerance, "iterations": solve.iterations,
                       "relative_residual": solve.relative_residual,
                       "capped": solve.capped, "fresh": solve.fresh})

    start, cpu = time.perf_counter(), time.process_time()
    with observe_solves(keep):
        result = reconstruct(data["faces"], data["edges"], data["lengths"], data["noisy"],
                             n_vertices=len(data["vertices"]), linear_solver="iterative")
    refinement = result.report["refinement"]
    summary = {"source": source, "faces": len(data["faces"]), "solves": solves,
               "seconds": time.perf_counter() - start, "cpu_seconds": time.process_time() - cpu,
               "report": refinement.get("linear_solver"),
               "energy_after": refinement.get("energy_after")}
    (folder / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def load_solve(source: str, k: int = -1, root: Path = CAPTURES) -> dict[str, Any]:
    """Captured solve ``k`` (negative: from the end) of ``source``: ``matrix`` (upper CSR
    float64), ``positions``, ``project``, ``rhs``, ``tolerance`` and its summary entry."""
    folder = capture_folder(source, root)
    solves = json.loads((folder / "summary.json").read_text())["solves"]
    k = k % len(solves)
    z = np.load(folder / f"solve{k}.npz")
    matrix = sp.csr_array((z["data"], z["indices"], z["indptr"]), shape=tuple(z["shape"]))
    with open(folder / f"solve{k}-projection.pkl", "rb") as fh:
        project = pickle.load(fh)
    return {"index": k, "matrix": matrix, "positions": z["positions"], "project": project,
            "rhs": z["rhs"], "tolerance": float(z["tolerance"]), **solves[k]}


# -- measurements (each in one process) ---------------------------------------------------

def solve_with(solve: dict[str, Any], hierarchy: HierarchyRules, tolerance: float,
               max_iterations: int) -> dict[str, Any]:
    """Set up ``hierarchy`` on a captured solve's matrix and solve it by the refinement's
    CG to ``tolerance`` (at most ``max_iterations``), BLAS on one thread as in the refinement
    (:meth:`solver.refine.Refiner.run`): setup and CG CPU seconds, iterations,
    relative residual, levels and operator complexity."""
    multigrid = Multigrid(max_iterations, DEFAULT_STEP_RULES.cg_resetup_growth,
                          DEFAULT_STEP_RULES.cg_setup_iterations, hierarchy)
    with threadpool_limits(limits=1, user_api="blas"):  # as the refinement runs
        cpu = time.process_time()
        operator = multigrid.operator(solve["matrix"], solve["positions"], solve["project"])
        setup = time.process_time() - cpu
        operator.tolerance = tolerance
        cpu = time.process_time()
        operator.solve(solve["rhs"])
    stats = multigrid.stats
    return {"setup_cpu_seconds": setup, "cg_cpu_seconds": time.process_time() - cpu,
            "iterations": stats.iterations[-1], "relative_residual": stats.residuals[-1],
            "capped": stats.capped > 0, "levels": stats.levels,
            "operator_complexity": stats.operator_complexity}


def measure_variant(source: str, name: str, k: int, tolerance: float, cap: int,
                    root: Path = CAPTURES) -> dict[str, Any]:
    """One ``variants`` row: variant ``name`` on ``source``'s captured solve ``k``."""
    solve = load_solve(source, k, root)
    row = solve_with(solve, variants()[name], tolerance, cap)
    return {"source": source, "variant": name, "solve": solve["index"],
            "order": solve["matrix"].shape[0], "tolerance": tolerance, **row}


def setup_price(source: str, k: int, repeats: int, root: Path = CAPTURES) -> dict[str, Any]:
    """The production setup's CPU seconds over one CG iteration's (medians of ``repeats``
    setups and solves to 1e-3 of ``source``'s captured solve ``k``)."""
    solve = load_solve(source, k, root)
    runs = [solve_with(solve, HIERARCHY_RULES, 1e-3, 10 * DEFAULT_STEP_RULES.cg_max_iterations)
            for _ in range(repeats)]
    setup = statistics.median(r["setup_cpu_seconds"] for r in runs)
    per_iteration = statistics.median(r["cg_cpu_seconds"] / max(r["iterations"], 1)
                                      for r in runs)
    return {"source": source, "solve": solve["index"], "order": solve["matrix"].shape[0],
            "repeats": repeats, "setup_cpu_seconds": setup,
            "iterations": runs[0]["iterations"], "iteration_cpu_seconds": per_iteration,
            "setup_in_iterations": setup / per_iteration,
            "cg_setup_iterations": DEFAULT_STEP_RULES.cg_setup_iterations}


def run_policy(source: str, policy: str, hierarchy: str = "production") -> dict[str, Any]:
    """The default answer of ``source`` by the iterative path with the hierarchy
    ``hierarchy`` (a :func:`variants` name: it replaces
    :data:`solver.refine.iterative_steps.HIERARCHY_RULES` in this process), set up again
    by the refinement's rule (``rule``), before every solve (``always``) or never again
    (``never``). The two others replace the rule (:meth:`Multigrid.solved`) in this process
    only: ``always`` reports every solve to it twice as capped (the first solve on a
    hierarchy only sets its baseline, the second makes it stale), ``never`` ignores every
    solve."""
    from solver import reconstruct
    from solver.refine import iterative_steps

    iterative_steps.HIERARCHY_RULES = variants()[hierarchy]
    if policy == "always":
        rule = Multigrid.solved

        def always(self: Multigrid, iterations: int, decades: float, capped: bool) -> None:
            rule(self, iterations, decades, True)
            rule(self, iterations, decades, True)

        Multigrid.solved = always
    elif policy == "never":
        Multigrid.solved = lambda self, i, decades, capped: None
    data = np.load(source_forms(source)[1])
    start, cpu = time.perf_counter(), time.process_time()
    result = reconstruct(data["faces"], data["edges"], data["lengths"], data["noisy"],
                         n_vertices=len(data["vertices"]), linear_solver="iterative")
    refinement = result.report["refinement"]
    cg = refinement["linear_solver"]
    return {"source": source, "policy": policy, "hierarchy": hierarchy,
            "faces": len(data["faces"]),
            "seconds": time.perf_counter() - start, "cpu_seconds": time.process_time() - cpu,
            "refine_seconds": result.report["timings"].get("refine"),
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "steps": refinement.get("iterations"), "cg_iterations": cg["cg_iterations"],
            "capped": cg["capped_solves"], "setups": cg["setups"],
            "setup_seconds": cg["setup_seconds"], "solve_seconds": cg["solve_seconds"],
            "energy_after": refinement.get("energy_after"), "converged": cg["converged"]}


# -- children and tables -----------------------------------------------------------------

def child(task: dict[str, Any], max_gb: float | None) -> dict[str, Any]:
    """Run ``task`` (``{"kind": ..., arguments}``) in a fresh process of this tree under an
    address-space limit of ``max_gb``; its row, or ``{"error": ...}``."""
    cmd = [sys.executable, "-m", "bench.gauss_newton_cg", "--child", json.dumps(task)]
    if max_gb:
        cmd[:0] = ["prlimit", f"--as={int(max_gb * 2**30)}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO,
                          env=dict(os.environ, PYTHONPATH=str(REPO)))
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
        return {**task, "error": "out of memory" if "MemoryError" in proc.stderr else tail[0]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_task(task: dict[str, Any]) -> dict[str, Any]:
    """What a child does with its task."""
    kind = task["kind"]
    root = Path(task.get("root", CAPTURES))
    if kind == "capture":
        return capture(task["source"], root)
    if kind == "variant":
        return measure_variant(task["source"], task["variant"], task["solve"],
                               task["tolerance"], task["cap"], root)
    if kind == "setup-price":
        return setup_price(task["source"], task["solve"], task["repeats"], root)
    if kind == "policy":
        return run_policy(task["source"], task["policy"], task.get("hierarchy", "production"))
    raise ValueError(f"unknown task {kind!r}")


def capture_table(rows: list[dict[str, Any]]) -> str:
    columns = [("source", "l"), ("faces", "r"), ("CPU s", "r"),
               ("solves: forcing term / CG iterations (set up)", "l"),
               ("report's CG iterations", "l"), ("E after", "l")]
    return "\n".join(markdown_table(columns, (
        [r["source"], r["faces"], f"{r['cpu_seconds']:.1f}",
         ", ".join(f"{s['tolerance']:.2g} / {s['iterations']}"
                   + (" (set up)" if s["fresh"] else "") for s in r["solves"]),
         r["report"]["cg_iterations"], f"{r['energy_after']:.10e}"] for r in rows)))


def variants_table(rows: list[dict[str, Any]]) -> str:
    columns = [("source", "l"), ("solve (order)", "l"), ("variant", "l"), ("levels", "r"),
               ("operator complexity", "r"), ("setup CPU s", "r"), ("CG iterations", "r"),
               ("CG CPU s", "r")]
    return "\n".join(markdown_table(columns, (
        [r["source"], "", r["variant"], r["error"]] if "error" in r else
        [r["source"], f"{r['solve']} ({r['order']})", r["variant"], r["levels"],
         f"{r['operator_complexity']:.2f}", f"{r['setup_cpu_seconds']:.1f}",
         f"{r['iterations']}" + (" (capped)" if r["capped"] else ""),
         f"{r['cg_cpu_seconds']:.1f}"] for r in rows)))


def policies_table(rows: list[dict[str, Any]]) -> str:
    columns = [("source", "l"), ("faces", "r"), ("hierarchy", "l"), ("policy", "l"),
               ("CPU s", "r"), ("seconds", "r"), ("peak MB", "r"), ("steps", "r"),
               ("CG iterations per step", "l"), ("setups (s)", "l"), ("CG s", "r"),
               ("E after", "l")]
    return "\n".join(markdown_table(columns, (
        [r["source"], "", r["hierarchy"], r["policy"], r["error"]] if "error" in r else
        [r["source"], r["faces"], r["hierarchy"], r["policy"], f"{r['cpu_seconds']:.1f}",
         f"{r['seconds']:.1f}", f"{r['peak_mb']:.0f}", r["steps"],
         ", ".join(map(str, r["cg_iterations"])),
         f"{r['setups']} ({r['setup_seconds']:.1f})", f"{r['solve_seconds']:.1f}",
         f"{r['energy_after']:.10e}"] for r in rows)))


def price_table(rows: list[dict[str, Any]]) -> str:
    columns = [("source", "l"), ("solve (order)", "l"), ("setup CPU s", "r"),
               ("CG iterations to 1e-3", "r"), ("CPU s per iteration", "r"),
               ("setup / iteration", "r"), ("`cg_setup_iterations`", "r")]
    return "\n".join(markdown_table(columns, (
        [r["source"], f"{r['solve']} ({r['order']})", f"{r['setup_cpu_seconds']:.2f}",
         r["iterations"], f"{r['iteration_cpu_seconds']:.4f}",
         f"{r['setup_in_iterations']:.0f}", f"{r['cg_setup_iterations']:g}"] for r in rows)))


def tasks(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The children a command line asks for, in order."""
    root = str(args.captures)
    out: list[dict[str, Any]] = []
    for source in args.sources:
        if args.command == "capture" or (
                args.command in ("variants", "setup-price")
                and not (capture_folder(source, args.captures) / "summary.json").exists()):
            out.append({"kind": "capture", "source": source, "root": root})
        if args.command == "variants":
            out += [{"kind": "variant", "source": source, "variant": name, "solve": args.solve,
                     "tolerance": args.tolerance, "cap": args.cap, "root": root}
                    for name in args.variants or variants()]
        elif args.command == "setup-price":
            out.append({"kind": "setup-price", "source": source, "solve": args.solve,
                        "repeats": args.repeats, "root": root})
        elif args.command == "policies":
            out += [{"kind": "policy", "source": source, "policy": p, "hierarchy": h}
                    for h in args.hierarchies for p in args.policies]
    return out


def header() -> str:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=REPO).stdout.strip()
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    return f"# {now}, commit {commit or '?'}, load {load_averages()}"


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        print(json.dumps(run_task(json.loads(sys.argv[2]))))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("command", choices=("capture", "variants", "policies", "setup-price"))
    parser.add_argument("sources", nargs="+", help="bench.scale level (0, 1) or MESH[:LEVEL]")
    parser.add_argument("--captures", type=Path, default=CAPTURES)
    parser.add_argument("--solve", type=int, default=-1,
                        help="which captured solve (default -1: the last)")
    parser.add_argument("--variants", nargs="+", choices=list(variants()), default=None)
    parser.add_argument("--tolerance", type=float, default=1e-3)
    parser.add_argument("--cap", type=int, default=1500, help="CG iterations at most")
    parser.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES))
    parser.add_argument("--hierarchies", nargs="+", choices=list(variants()),
                        default=["production"], help="policies: with each of these")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-gb", type=float, default=8.0,
                        help="address-space limit of each child (GB; 0: none)")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print(header(), flush=True)
    rows: dict[str, list[dict[str, Any]]] = {}
    for task in tasks(args):
        row = child(task, args.max_gb)
        rows.setdefault(task["kind"], []).append(row)
        print(json.dumps(row), flush=True)
    print(header())
    if args.markdown:
        tables = {"capture": capture_table, "variant": variants_table,
                  "policy": policies_table, "setup-price": price_table}
        for kind, kind_rows in rows.items():
            ok = [r for r in kind_rows if kind != "capture" or "error" not in r]
            print("\n" + tables[kind](ok))


if __name__ == "__main__":
    main()
