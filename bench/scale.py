"""Reconstruction at scan size: exact, linear and default answers from ~100K to 1.6M faces.

A shared scan (``nefertiti.obj``, 99 938 faces, closed genus 0) is subdivided 4:1 by edge
midpoints (trimesh) 0, 1 and 2 times (100K, 400K, 1.6M faces; ``--levels 3`` adds 6.4M).
Its forms, exact and with every dihedral angle + N(0, 1e-3) rad, are cached under
``/tmp/ffs-scale`` (never in git). Each case runs in a fresh child process that reports its
wall time per stage (``report["timings"]``) and its CPU time (user + system, less
sensitive to the load of a shared machine than the wall time), the peak RSS of the whole
process (getrusage ``ru_maxrss``) and the peak RSS reached during each stage (a sampling
thread reading ``/proc/self/status`` every 5 ms, attributed to the stage the progress
callback last named), the solve path and the refinement's factorization and iteration counts.

Cases:

* ``exact``: exact forms, default options: the tree integration (no factorization).
* ``linear``: noisy forms, ``refine=False``: one factorization (plus the orthonormalization).
* ``default``: noisy forms, default options: the refined (nearest-surface) answer.

Usage (from the repository root)::

    python -m bench.scale                      # levels 0 1 2, every case
    python -m bench.scale --levels 0 1 --cases exact linear
    python -m bench.scale --max-gb 10          # address-space limit of each child
    python -m bench.scale --markdown           # also print the tables for bench/README.md
    python -m bench.scale --baseline /tmp/old  # each case also run by another tree, before
    python -m bench.scale --cases default-iterative --start-tolerances 1e-8 1e-4 1e-3
    python -m bench.scale --allocators glibc tuned  # glibc's malloc, and fixed thresholds

``--allocators tuned`` runs a case with glibc's mmap and trim thresholds fixed at 128 KiB
(:func:`fixed_malloc_thresholds`; glibc raises its mmap threshold to every freed mapped
block's size, up to 32 MiB, so freed arrays stay in the process's heap): measured, it does
not change the peaks (bench/README.md, "Iterative linear path"), so the service does not
set it.

A child that runs out of its address-space limit is reported as ``out of memory`` (the
parent survives; the OOM killer is never reached).

While a case runs, its stages and the refinement's iterations are written to stderr as they
come, with the elapsed seconds and the RSS (a run of hours at 5M faces shows where it is)::

    [bunny level 1 default-iterative]       1.9 s  refine  (RSS 172 MB)
    [bunny level 1 default-iterative]       4.2 s  refine iteration 1: E 7.787548e-05, ...
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from bench.common import (
    REPO,
    SHARED_MESHES,
    load_averages,
    markdown_table,
    scaling_exponent,
)

CACHE = Path(os.environ.get("FFS_SCALE_CACHE", "/tmp/ffs-scale"))
"""Where the subdivided meshes and their forms are cached (outside the repository)."""
BASE = "nefertiti.obj"
NOISE = 1e-3
PROGRESS_MARK = "progress: "
"""How a child's progress lines on stderr begin (:class:`StageMemory`): the parent forwards
them as they come (:func:`child`) and leaves them out of an error's last line."""
CASES = ("exact", "linear", "default", "linear-direct", "linear-iterative",
         "default-direct", "default-iterative")
"""``linear`` and ``default`` choose the linear solver by size (``linear_solver="auto"``);
the ``-direct`` and ``-iterative`` cases force it (``default-iterative``: Eq. 5 and the
refinement's Gauss-Newton steps by CG, no factorization)."""


def forms_file(level: int, base: str = BASE) -> Path:
    """The cached forms of ``base`` subdivided ``level`` times (made on first use)."""
    path = CACHE / f"{Path(base).stem}-s{level}.npz"
    if path.exists():
        return path
    import trimesh

    from solver import fundamental_forms

    mesh = trimesh.load(SHARED_MESHES / base, process=False)
    V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    for _ in range(level):
        V, F = trimesh.remesh.subdivide(V, F)
    forms = fundamental_forms(V, F)
    noisy = forms.angles + np.random.default_rng(0).normal(scale=NOISE, size=len(forms.angles))
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, vertices=V, faces=np.asarray(forms.faces), edges=forms.edges,
             lengths=forms.lengths, angles=forms.angles, noisy=noisy)
    tmp.rename(path)
    return path


class StageMemory:
    """Peak RSS (MB) per stage, sampled by a thread every ``period`` seconds; the stage is
    the one ``progress`` last named. With a ``log`` (the child's stderr), every new stage
    and every refinement iteration (``progress.iteration``) is also written there as one
    line starting with :data:`PROGRESS_MARK`: elapsed seconds, the stage or the
    iteration's energy, and the RSS, so that a run of hours shows where it is."""

    def __init__(self, period: float = 0.005, log: TextIO | None = None) -> None:
        self.stage = "load"
        self.peak: dict[str, float] = {}
        self._log = log
        self._start = time.perf_counter()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)
        self._thread.start()

    def __call__(self, stage: str, fraction: float) -> None:
        self._sample()
        if stage != self.stage:
            self._write(f"{stage}")
        self.stage = stage

    def iteration(self, detail: dict) -> None:
        """The refinement's per-iteration hook (``solver.refine.refiner``)."""
        self._write(f"refine iteration {detail['iteration']}: E {detail['energy']:.6e}, "
                    f"{detail['factorizations']} factorizations")

    def _write(self, what: str) -> None:
        if self._log is not None:
            elapsed = time.perf_counter() - self._start
            print(f"{PROGRESS_MARK}{elapsed:9.1f} s  {what}  (RSS {self._rss():.0f} MB)",
                  file=self._log, flush=True)

    @staticmethod
    def _rss() -> float:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        return 0.0

    def _sample(self) -> None:
        mb = self._rss()
        self.peak[self.stage] = max(self.peak.get(self.stage, 0.0), mb)

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            self._sample()

    def stop(self) -> dict[str, float]:
        self._stop.set()
        self._thread.join()
        self._sample()
        return {k: round(v) for k, v in self.peak.items()}


def case_options(case: str) -> dict:
    """The reconstruct options of a case."""
    kind, _, solver = case.partition("-")
    options: dict = {"refine": False} if kind == "linear" else {}
    if solver:
        options["linear_solver"] = solver
    return options


def run_case(level: int, case: str, base: str = BASE) -> dict:
    """One case in this process; returns its measurements (a JSON-able dict)."""
    from solver import reconstruct

    memory = StageMemory(log=sys.stderr)
    data = np.load(forms_file(level, base))
    faces, edges, lengths = data["faces"], data["edges"], data["lengths"]
    angles = data["angles"] if case == "exact" else data["noisy"]
    n_vertices = len(data["vertices"])
    original = data["vertices"]
    options = case_options(case)
    start_tolerance = os.environ.get("FFS_SCALE_START_TOLERANCE")
    if start_tolerance:  # --start-tolerance: the rules in force, with another start's
        import dataclasses
        import importlib

        module = importlib.import_module("solver.reconstruct")  # not the function
        module.LINEAR_SOLVER_RULES = dataclasses.replace(
            module.LINEAR_SOLVER_RULES, start_tolerance=float(start_tolerance))
    start, cpu = time.perf_counter(), time.process_time()
    result = reconstruct(faces, edges, lengths, angles, n_vertices=n_vertices,
                         progress=memory, **options)
    wall = time.perf_counter() - start
    cpu = time.process_time() - cpu
    report = result.report
    refinement = report.get("refinement") or {}
    linear_solver = report.get("linear_solver") or {}
    return {
        "base": Path(base).stem, "level": level, "case": case, "faces": len(faces),
        "seconds": wall, "linear_solver": linear_solver.get("method"),
        "cg_iterations": linear_solver.get("iterations"),
        "cg_residual": linear_solver.get("relative_residual"),
        "cg_tolerance": linear_solver.get("tolerance"),
        "distance": rigid_distance(result.vertices, original),
        "cpu_seconds": cpu,
        "timings": {k: round(v, 3) for k, v in report["timings"].items()},
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "stage_peak_mb": memory.stop(), "solve_path": report["solve_path"],
        "factorizations": refinement.get("factorizations"),
        "iterations": refinement.get("iterations"),
        "converged": refinement.get("converged"),
        "refine_cg_iterations": (refinement.get("linear_solver") or {}).get("cg_iterations"),
        "refine_setups": (refinement.get("linear_solver") or {}).get("setups"),
        "energy_after": refinement.get("energy_after"),
        "refinement": refinement.get("reason") or refinement.get("stopped"),
    }


def rigid_distance(X: np.ndarray, Y: np.ndarray) -> float:
    """max |R X + t - Y| over vertices after the best rigid alignment (Kabsch), divided by
    the bounding-box diagonal of Y: the answer's distance to the mesh the forms came from."""
    Xc, Yc = X - X.mean(axis=0), Y - Y.mean(axis=0)
    U, _, Vt = np.linalg.svd(Xc.T @ Yc)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return float(np.abs(Xc @ R - Yc).max() / np.linalg.norm(Y.max(axis=0) - Y.min(axis=0)))


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
"""glibc's ``mallopt`` parameters (malloc.h)."""


def fixed_malloc_thresholds(threshold: int = 128 * 1024) -> bool:
    """Fix glibc's mmap and trim thresholds at ``threshold`` bytes in this process (a block
    of that size or more is mapped on its own and unmapped when freed; glibc's dynamic raise
    is off). True where glibc took both (False elsewhere: nothing changed)."""
    import ctypes
    import ctypes.util

    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, threshold)) and bool(
        mallopt(M_TRIM_THRESHOLD, threshold))


def run_forwarding_progress(cmd: list[str], env: dict, cwd: Path,
                            prefix: str) -> tuple[int, str, str]:
    """Run ``cmd`` to its end; its progress lines (:data:`PROGRESS_MARK`) are written to this
    process's stderr, after ``prefix``, as they come. Returns the exit status, the whole
    stdout and the whole stderr (progress lines included)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=cwd)
    lines: list[str] = []

    def forward() -> None:
        for line in proc.stderr:
            lines.append(line)
            if line.startswith(PROGRESS_MARK):
                print(prefix + line[len(PROGRESS_MARK):], end="", file=sys.stderr, flush=True)

    reader = threading.Thread(target=forward, daemon=True)
    reader.start()
    stdout = proc.stdout.read()
    returncode = proc.wait()
    reader.join()
    return returncode, stdout, "".join(lines)


def failure(returncode: int, stderr: str) -> str:
    """A failed child's error cell: ``out of memory`` where it ran out of its address space,
    else its last stderr line that is not progress, else its exit status."""
    if "MemoryError" in stderr or "Cannot allocate" in stderr:
        return "out of memory"
    errors = [line for line in stderr.strip().splitlines() if not line.startswith(PROGRESS_MARK)]
    return (errors[-1:] or [f"exit {returncode}"])[0]


def child(level: int, case: str, max_gb: float | None, base: str = BASE,
          tree: Path | None = None, start_tolerance: float | None = None,
          allocator: str | None = None) -> dict:
    """Run one case in a fresh process under an address-space limit of ``max_gb``, with the
    library (and this bench) of ``tree`` (default: this repository); a row from another
    tree has its case suffixed ``(baseline)``. ``allocator``: ``"glibc"`` (the default) or
    ``"tuned"`` (:func:`fixed_malloc_thresholds`; the case is suffixed)."""
    forms_file(level, base)  # made once, in the parent, outside the measured process
    cmd = [sys.executable, "-m", "bench.scale", "--child", str(level), case, "--base", base]
    if max_gb:
        cmd[:0] = ["prlimit", f"--as={int(max_gb * 2**30)}"]
    root = REPO if tree is None else tree
    env = dict(os.environ, PYTHONPATH=str(root))
    if start_tolerance is not None:
        env["FFS_SCALE_START_TOLERANCE"] = repr(start_tolerance)
    if allocator is not None:
        env["FFS_SCALE_ALLOCATOR"] = allocator
    label = case if tree is None else f"{case} (baseline)"
    if start_tolerance is not None:
        label += f" (start {start_tolerance:g})"
    if allocator == "tuned":
        label += " (fixed malloc thresholds)"
    returncode, stdout, stderr = run_forwarding_progress(
        cmd, env, root, f"[{Path(base).stem} level {level} {label}] ")
    if returncode != 0:
        return {"base": Path(base).stem, "level": level, "case": label,
                "error": failure(returncode, stderr)}
    row = json.loads(stdout.strip().splitlines()[-1])
    row["case"] = label
    return row


def _error_cells(r: dict) -> list[Any]:
    return [r.get("base", ""), f"level {r['level']}", r["case"], r["error"]]


def _cells(r: dict) -> list[Any]:
    """One case's cells of :func:`markdown`'s table."""
    def given(value: Any) -> Any:
        return "-" if value is None else value

    cg = (f"{r['cg_iterations']} ({r['cg_residual']:.1e})"
          if r.get("cg_iterations") is not None else "-")
    return [r.get("base", ""), r["faces"], r["case"], r["solve_path"], f"{r['seconds']:.2f}",
            f"{r.get('cpu_seconds', float('nan')):.2f}", f"{r['faces'] / r['seconds']:,.0f}",
            f"{r['peak_mb']:.0f}", cg, given(r["factorizations"]), given(r["iterations"]),
            ", ".join(f"{k} {v:.2f}" for k, v in r["timings"].items()),
            ", ".join(f"{k} {v}" for k, v in r["stage_peak_mb"].items())]


def markdown(rows: list[dict]) -> str:
    """The tables of bench/README.md: one row per case, then the fitted exponents."""
    columns = [("mesh", "l"), ("faces", "r"), ("case", "l"), ("path", "l"), ("seconds", "r"),
               ("CPU s", "r"), ("faces/s", "r"), ("peak MB", "r"),
               ("CG iterations (residual)", "l"), ("factorizations", "r"), ("iterations", "r"),
               ("stages (s)", "l"), ("stage peaks (MB)", "l")]
    lines = markdown_table(columns, (_error_cells(r) if "error" in r else _cells(r)
                                     for r in rows))
    lines.append("")
    for base, case in sorted({(r.get("base", ""), r["case"]) for r in rows}):
        ok = [r for r in rows if r["case"] == case and r.get("base", "") == base
              and "error" not in r]
        if len(ok) >= 2:
            k_t = scaling_exponent([r["faces"] for r in ok], [r["seconds"] for r in ok])
            k_m = scaling_exponent([r["faces"] for r in ok], [r["peak_mb"] for r in ok])
            lines.append(f"- {base} {case}: time ~ faces^{k_t:.2f}, peak RSS ~ faces^{k_m:.2f} "
                         f"({ok[0]['faces']} to {ok[-1]['faces']} faces)")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--max-gb", type=float, default=10.0,
                        help="address-space limit of each child (GB; 0: none)")
    parser.add_argument("--bases", nargs="+", default=[BASE],
                        help="shared meshes to subdivide (e.g. nefertiti.obj armadillo.obj)")
    parser.add_argument("--base", default=BASE, help=argparse.SUPPRESS)
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="another tree (e.g. `git archive <commit> solver bench | tar -x "
                             "-C DIR`): every case also runs with its library, just before")
    parser.add_argument("--start-tolerances", type=float, nargs="+", default=None,
                        help="run every case with each of these tolerances of the iterative "
                             "solve that starts the refinement (LinearSolverRules."
                             "start_tolerance), e.g. 1e-8 1e-4 1e-3")
    parser.add_argument("--allocators", nargs="+", default=None,
                        choices=("glibc", "tuned"),
                        help="run every case with each: glibc's malloc (the default) or "
                             "its mmap and trim thresholds fixed at 128 KiB (tuned)")
    parser.add_argument("--child", nargs=2, metavar=("LEVEL", "CASE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        if os.environ.get("FFS_SCALE_ALLOCATOR") == "tuned":
            fixed_malloc_thresholds()
        print(json.dumps(run_case(int(args.child[0]), args.child[1], args.base)))
        return
    print(f"# load {load_averages()}", flush=True)
    rows = []
    for base in args.bases:
        for case in args.cases:
            for level in args.levels:
                for tree in ([args.baseline] if args.baseline else []) + [None]:
                    for tolerance in args.start_tolerances or [None]:
                        for allocator in args.allocators or [None]:
                            row = child(level, case, args.max_gb, base, tree, tolerance,
                                        allocator)
                            rows.append(row)
                            print(json.dumps(row), flush=True)
    print(f"# load {load_averages()}")
    if args.markdown:
        print(markdown(rows))


if __name__ == "__main__":
    main()
