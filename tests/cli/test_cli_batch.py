"""Batches: 21 meshes with a broken one among them, in-process with ``-j 2`` (two worker
processes, seen by their PIDs and overlapping run times) and on a server with ``-j 2``
(concurrent jobs); the broken file is named, the rest are written, exit code 1."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import solver
from solver.mesh.io import load_mesh_file, save_mesh
from tests.helpers.meshes import grid

N_GOOD = 20


def write_batch(folder: Path) -> list[str]:
    """20 curved open grids (different sizes and bumps) and one OBJ whose fourth vertex has a
    NaN coordinate (a file the reader parses and the solver refuses: a face that repeats a
    vertex is dropped and reported since the weld), third from last in name order."""
    folder.mkdir()
    names = []
    for k in range(N_GOOD):
        V, F = grid(10 + k % 5, 8 + k % 3, width=1.5, height=1.0)
        V[:, 2] = 0.1 * (1 + k / 10) * np.sin(3 * V[:, 0]) * np.cos(4 * V[:, 1])
        name = f"grid-{k:02d}.obj"
        (folder / name).write_bytes(save_mesh(V, F, "obj"))
        names.append(name)
    (folder / "grid-17b.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 1 0\n"
                                         "f 1 2 3\nf 2 4 3\n")
    return sorted([*names, "grid-17b.obj"])


def assert_batch_result(result, workdir: Path, out: str) -> None:
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(errors) == 1, result.stderr
    assert "grid-17b.obj" in errors[0] and "vertex 3" in errors[0]
    written = sorted(p.name for p in (workdir / out).iterdir())
    assert written == [f"grid-{k:02d}.npz" for k in range(N_GOOD)]
    assert "20 of 21 done, 1 failed" in result.stdout


def test_batch_in_parallel_processes_with_one_broken_file(ffs, workdir):
    names = write_batch(workdir / "in")
    result = ffs("flatten", *[f"in/{n}" for n in names], "-o", "local/{stem}.npz", "-j", "2",
                 "--report", "report.json")
    assert_batch_result(result, workdir, "local")
    rows = json.loads((workdir / "report.json").read_text())["files"]
    assert [r["status"] for r in rows].count("failed") == 1
    assert rows[names.index("grid-17b.obj")]["status"] == "failed"
    done = [r for r in rows if r["status"] == "ok"]
    pids = {r["pid"] for r in done}
    assert len(pids) == 2, pids  # two worker processes, neither of them the command's
    overlapping = any(a["pid"] != b["pid"] and a["started"] < b["finished"]
                      and b["started"] < a["finished"] for a in done for b in done)
    assert overlapping, "no two files ran at the same time"
    for k in (0, 7, 19):  # what was written is the library's flattening
        V, F = load_mesh_file(workdir / "in" / f"grid-{k:02d}.obj")
        uv = np.load(workdir / "local" / f"grid-{k:02d}.npz")["uv"]
        assert np.abs(uv - solver.parameterize(V, F).uv).max() < 1e-6


def test_batch_on_the_server_with_one_broken_file(ffs, server, workdir):
    names = write_batch(workdir / "in")
    inputs = [f"in/{n}" for n in names]
    remote = ffs("flatten", *inputs, "-o", "remote/{stem}.npz", "-j", "2", "--server", server)
    assert_batch_result(remote, workdir, "remote")
    local = ffs("flatten", *inputs, "-o", "local/{stem}.npz", "-j", "2")
    assert_batch_result(local, workdir, "local")
    for k in range(N_GOOD):  # -j 2 locally: 1 BLAS thread per worker, as on the server
        uv_local = np.load(workdir / "local" / f"grid-{k:02d}.npz")["uv"]
        uv_remote = np.load(workdir / "remote" / f"grid-{k:02d}.npz")["uv"]
        assert np.abs(uv_local - uv_remote).max() <= 1e-12


def test_fail_fast_stops_at_the_first_failure(ffs, workdir):
    """The broken file first: after it fails no file starts. Only those already running in
    the other workers when it failed (at most jobs - 1) may finish or be stopped; without
    --fail-fast all 20 would be written."""
    jobs = 1
    names = write_batch(workdir / "in")
    broken_first = ["in/grid-17b.obj", *[f"in/{n}" for n in names if n != "grid-17b.obj"]]
    result = ffs("forms", *broken_first, "-o", "out/{stem}.npz", "--fail-fast",
                 "-j", str(jobs), "--report", "report.json")
    assert result.returncode == 1
    rows = json.loads((workdir / "report.json").read_text())["files"]
    assert rows[0]["status"] == "failed"
    statuses = [r["status"] for r in rows[1:]]
    assert set(statuses) <= {"skipped", "ok", "stopped"}
    assert statuses.count("skipped") >= N_GOOD - (jobs - 1), statuses
    assert statuses.count("ok") <= jobs - 1
    assert len(list((workdir / "out").glob("*.npz"))) == statuses.count("ok")
