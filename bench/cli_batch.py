"""A batch of small meshes through the command line, in-process and on a server, against a
plain Python loop over ``solver`` in the same run.

    python -m bench.cli_batch [--files 100] [--command flatten] [--repeats 3]

The meshes are curved open grids of 160-390 faces (written as OBJ to a temporary folder).
Each variant handles every file: read, compute, write.

* ``loop``: one Python process, ``for path in files: load_mesh_file -> solver.<op> ->
  save``, timed inside the process (no interpreter start-up);
* ``ffs -j 1`` and ``ffs -j 2``: the command line in-process (``-j 2``: two spawned worker
  processes with one BLAS thread each), wall time of the whole command;
* ``ffs --server -j 2``: the same files as concurrent jobs on a real uvicorn on loopback
  (``FFS_WORKERS=2``), started before the clock.

Prints a Markdown table: median wall seconds of ``--repeats`` runs, files per second and the
ratio loop / variant (> 1: faster than the loop), and the machine's load.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import solver
from bench.common import REPO
from bench.servers import uvicorn
from solver.mesh.io import load_mesh_file, save_mesh
from tests.helpers.meshes import grid


def write_meshes(folder: Path, count: int) -> list[Path]:
    paths = []
    for k in range(count):
        V, F = grid(8 + k % 8, 10 + k % 4, width=1.5, height=1.0)
        V[:, 2] = 0.1 * (1 + (k % 10) / 10) * np.sin(3 * V[:, 0]) * np.cos(4 * V[:, 1])
        path = folder / f"mesh-{k:03d}.obj"
        path.write_bytes(save_mesh(V, F, "obj"))
        paths.append(path)
    return paths


def python_loop(paths: list[Path], out: Path, command: str) -> float:
    """The plain loop a library user writes; seconds."""
    out.mkdir(exist_ok=True)
    started = time.perf_counter()
    for path in paths:
        V, F = load_mesh_file(path)
        if command == "flatten":
            uv = solver.parameterize(V, F).uv
            np.savez(out / f"{path.stem}.npz", uv=uv)
        else:
            forms = solver.fundamental_forms(V, F)
            np.savez(out / f"{path.stem}.npz", faces=forms.faces, edges=forms.edges,
                     lengths=forms.lengths, angles=forms.angles)
    return time.perf_counter() - started


def ffs_command() -> list[str]:
    script = shutil.which("ffs")
    return [script] if script else [sys.executable, "-m", "ffs"]


def run_ffs(paths: list[Path], out: Path, command: str, *options: str) -> float:
    """Wall seconds of one ``ffs`` command over every file (must succeed)."""
    env = {k: v for k, v in os.environ.items() if k != "FFS_SERVER"}
    env["PYTHONPATH"] = str(REPO)
    started = time.perf_counter()
    result = subprocess.run([*ffs_command(), command, *map(str, paths), "-o",
                             str(out / "{stem}.npz"), "-q", *options], env=env,
                            capture_output=True, text=True)
    elapsed = time.perf_counter() - started
    if result.returncode != 0:
        raise RuntimeError(f"ffs {' '.join(options)} failed: {result.stderr}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--files", type=int, default=100)
    parser.add_argument("--command", choices=("flatten", "forms"), default="flatten")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "in").mkdir()
        paths = write_meshes(folder / "in", args.files)
        faces = [len(load_mesh_file(p)[1]) for p in paths]
        times: dict[str, list[float]] = {}
        load = [os.getloadavg()[0]]
        with uvicorn({"FFS_WORKERS": "2"}, workers_ready=2) as base:
            variants = {
                "python loop over solver": lambda out: python_loop(paths, out, args.command),
                "ffs -j 1": lambda out: run_ffs(paths, out, args.command, "-j", "1"),
                "ffs -j 2": lambda out: run_ffs(paths, out, args.command, "-j", "2"),
                "ffs --server -j 2": lambda out: run_ffs(paths, out, args.command, "-j", "2",
                                                         "--server", base),
            }
            python_loop(paths[:3], folder / "warm", args.command)  # imports, first calls
            for repeat in range(args.repeats):
                for name, variant in variants.items():
                    out = folder / f"out-{repeat}-{len(times.get(name, []))}-{abs(hash(name))}"
                    times.setdefault(name, []).append(variant(out))
                    load.append(os.getloadavg()[0])
        loop = statistics.median(times["python loop over solver"])
        print(f"{args.files} meshes ({min(faces)}-{max(faces)} faces), `{args.command}`, "
              f"median of {args.repeats}; load {min(load):.1f}-{max(load):.1f}\n")
        print("| variant | seconds (median) | all runs | files/s | loop / variant |")
        print("|---|---:|---|---:|---:|")
        for name, values in times.items():
            median = statistics.median(values)
            runs = ", ".join(f"{v:.2f}" for v in values)
            print(f"| {name} | {median:.2f} | {runs} | {args.files / median:.1f} | "
                  f"{loop / median:.2f}x |")


if __name__ == "__main__":
    main()
