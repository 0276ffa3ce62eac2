"""Each ``ffs`` command on real meshes, in-process and with ``--server`` against a real
uvicorn: the files written are checked against the library's answers and against each other
(the same vertices to 1e-12; ``--threads 1`` gives the local run the BLAS thread count of the
server's workers, so the round-off is the same).

The truth is independent where it exists: reconstructed forms of a mesh give that mesh back
after rigid alignment, a converted PLY holds the file's float64 vertices bit for bit, a blend
at t = 0 is mesh A.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

import solver
from solver.mesh.io import load_mesh_file
from tests.helpers import REPO
from tests.helpers.servers import free_port
from tests.helpers.service import rigid_error

SAME = 1e-12


def run_both(ffs, server: str, workdir: Path, command: str, inputs: list[str], output: str,
             *options: str) -> tuple[Path, Path]:
    """``ffs command inputs -o local/output`` in-process and ``-o remote/output --server``;
    both must succeed. Returns the two output paths (templates: the folders)."""
    local = ffs(command, *inputs, "-o", f"local/{output}", "--threads", "1", *options)
    assert local.returncode == 0, local.stderr
    remote = ffs(command, *inputs, "-o", f"remote/{output}", "--server", server, *options)
    assert remote.returncode == 0, remote.stderr
    assert "Traceback" not in local.stderr + remote.stderr
    return workdir / "local" / output, workdir / "remote" / output


def test_forms_json_and_npz_are_the_librarys(ffs, server, workdir):
    V, F = load_mesh_file(workdir / "decimated-knight.off")
    truth = solver.fundamental_forms(V, F)
    for output in ("knight.npz", "knight.json"):
        local, remote = run_both(ffs, server, workdir, "forms", ["decimated-knight.off"], output)
        for path in (local, remote):
            if path.suffix == ".npz":
                data = dict(np.load(path))
            else:
                data = {k: np.asarray(v) for k, v in json.loads(path.read_text()).items()}
            # + each part's placement (issue 40): one part, anchored at face 0
            placement = ["placement"] if path.suffix == ".json" else [
                "placement_faces", "placement_frames", "placement_origins"]
            assert sorted(data) == sorted(["angles", "edges", "faces", "lengths", *placement])
            np.testing.assert_array_equal(data["edges"], truth.edges)
            np.testing.assert_array_equal(data["faces"], truth.faces)
            np.testing.assert_array_equal(data["lengths"], truth.lengths)
            np.testing.assert_array_equal(data["angles"], truth.angles)


def test_check_reports_integrability_and_require_integrable_fails(ffs, server, workdir):
    result = ffs("check", "decimated-knight.off", "--report", "check.json")
    assert result.returncode == 0, result.stderr
    assert "integrable" in result.stdout
    report = json.loads((workdir / "check.json").read_text())
    assert report["files"][0]["integrable"] is True
    assert report["files"][0]["max_defect"] < 1e-10

    V, F = load_mesh_file(workdir / "decimated-knight.off")
    forms = solver.fundamental_forms(V, F)
    np.savez(workdir / "bent.npz", faces=forms.faces, edges=forms.edges,
             lengths=forms.lengths, angles=0.8 * forms.angles)
    for where in ([], ["--server", server]):
        result = ffs("check", "bent.npz", "--require-integrable", *where)
        assert result.returncode == 1
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "bent.npz" in lines[0] and "not integrable" in lines[0]
        assert "Traceback" not in result.stderr


def test_reconstruct_gives_the_mesh_back_and_refines_bent_forms(ffs, server, workdir):
    V, F = load_mesh_file(workdir / "decimated-knight.off")
    forms = solver.fundamental_forms(V, F)
    assert ffs("forms", "decimated-knight.off", "-o", "knight.json").returncode == 0
    local, remote = run_both(ffs, server, workdir, "reconstruct", ["knight.json"], "knight.ply")
    for path in (local, remote):
        W, G = load_mesh_file(path)
        np.testing.assert_array_equal(G, F)
        assert rigid_error(W, V) < 1e-9  # the forms' own surface
    assert np.abs(load_mesh_file(local)[0] - load_mesh_file(remote)[0]).max() <= SAME

    np.savez(workdir / "bent.npz", faces=forms.faces, edges=forms.edges,
             lengths=forms.lengths, angles=0.9 * forms.angles)
    local, remote = run_both(ffs, server, workdir, "reconstruct", ["bent.npz"], "bent.obj",
                             "--report", "bent-report.json")
    report = json.loads((workdir / "bent-report.json").read_text())["files"][0]
    assert report["refined"] is True and report["length_error"] < 0.05
    library = solver.reconstruct(forms.faces, forms.edges, forms.lengths, 0.9 * forms.angles)
    W_local, W_remote = load_mesh_file(local)[0], load_mesh_file(remote)[0]
    assert np.abs(W_local - W_remote).max() <= SAME
    assert rigid_error(W_local, library.vertices) < 1e-6  # this process: other BLAS threads


def test_deform_moves_the_handles_like_the_library(ffs, server, workdir):
    V, F = load_mesh_file(workdir / "decimated-knight.off")
    handles = [0, 100, 200, 300]
    targets = V[handles] + [[0, 0, 0], [0, 0, 0], [0.05, 0, 0], [0, 0.1, 0]]
    (workdir / "handles.json").write_text(json.dumps(
        [{"vertex": h, "position": p} for h, p in zip(handles, targets.tolist(), strict=True)]))
    local, remote = run_both(ffs, server, workdir, "deform", ["decimated-knight.off"],
                             "{stem}.ply", "--handles", "handles.json")
    local, remote = (p.with_name("decimated-knight.ply") for p in (local, remote))
    W_local, W_remote = load_mesh_file(local)[0], load_mesh_file(remote)[0]
    assert np.abs(W_local - W_remote).max() <= SAME
    np.testing.assert_allclose(W_local[handles], targets, atol=1e-9)
    library = solver.deform(V, F, handles, targets)
    assert np.abs(W_local - library.vertices).max() < 1e-6


def test_flatten_gives_the_librarys_layout(ffs, server, workdir):
    V, F = load_mesh_file(workdir / "face.off")
    local, remote = run_both(ffs, server, workdir, "flatten", ["face.off"], "face.npz")
    uv_local, uv_remote = np.load(local)["uv"], np.load(remote)["uv"]
    assert np.abs(uv_local - uv_remote).max() <= SAME
    assert len(np.load(local)["flipped_faces"]) == 0
    library = solver.parameterize(V, F)
    assert rigid_error(np.column_stack([uv_local, np.zeros(len(V))]),
                       np.column_stack([library.uv, np.zeros(len(V))])) < 1e-6
    local, remote = run_both(ffs, server, workdir, "flatten", ["face.off"], "face.obj",
                             "--flat")
    flat, faces = load_mesh_file(local)
    np.testing.assert_array_equal(faces, F)
    np.testing.assert_array_equal(flat[:, 2], 0.0)
    np.testing.assert_array_equal(flat[:, :2], uv_local)


def test_blend_writes_one_mesh_per_t(ffs, server, workdir):
    V, F = load_mesh_file(workdir / "decimated-knight.off")
    bent = V.copy()
    bent[:, 2] += 0.1 * np.sin(3 * V[:, 0])
    (workdir / "bent.obj").write_bytes(solver.mesh.io.save_mesh(bent, F, "obj"))
    local, remote = run_both(ffs, server, workdir, "blend",
                             ["decimated-knight.off", "bent.obj"], "blend-{t}.ply",
                             "-t", "0", "0.5", "1")
    for t in ("0", "0.5", "1"):
        W_local = load_mesh_file(local.with_name(f"blend-{t}.ply"))[0]
        W_remote = load_mesh_file(remote.with_name(f"blend-{t}.ply"))[0]
        assert np.abs(W_local - W_remote).max() <= SAME
    assert rigid_error(load_mesh_file(local.with_name("blend-0.ply"))[0], V) < 1e-6
    assert rigid_error(load_mesh_file(local.with_name("blend-1.ply"))[0], bent) < 1e-6


@pytest.mark.parametrize("output", ["knight.ply", "knight.glb", "knight.npz"])
def test_convert_keeps_the_vertices(ffs, server, workdir, output):
    V, F = load_mesh_file(workdir / "decimated-knight.off")
    local, remote = run_both(ffs, server, workdir, "convert", ["decimated-knight.off"], output)
    for path in (local, remote):
        if path.suffix == ".npz":
            W, G = np.load(path)["vertices"], np.load(path)["faces"]
        else:
            W, G = load_mesh_file(path)
        np.testing.assert_array_equal(G, F)
        if path.suffix == ".glb":  # float32 positions
            np.testing.assert_allclose(W, V, rtol=1e-6, atol=1e-6)
        else:
            np.testing.assert_array_equal(W, V)


def test_version_and_help(ffs):
    version = ffs("--version")
    assert version.returncode == 0 and version.stdout.startswith("ffs ")
    for command in ("forms", "check", "reconstruct", "deform", "flatten", "blend", "convert",
                    "serve"):
        helped = ffs(command, "--help")
        assert helped.returncode == 0 and "usage: ffs " + command in helped.stdout


def test_serve_runs_the_service_until_sigterm(workdir):
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    script = shutil.which("ffs")
    command = [script] if script else [sys.executable, "-m", "ffs"]
    proc = subprocess.Popen([*command, "serve", "--port", str(port), "--workers", "1"],
                            cwd=workdir, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline, ready = time.monotonic() + 60, None
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                ready = httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2)
                if ready.status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        assert ready is not None and ready.json()["workers"] == 1
        proc.send_signal(signal.SIGTERM)
        # uvicorn shuts down, then re-raises the signal: ended by SIGTERM, not by a crash
        assert proc.wait(timeout=30) in (0, -signal.SIGTERM)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
