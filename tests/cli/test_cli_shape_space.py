"""``ffs blend`` of K meshes (--weights) into an animated GLB or one file per row, ``ffs
mean`` and ``ffs transfer``, in-process and on a real service, against the library."""

from __future__ import annotations

import json
import shutil

import numpy as np
import trimesh

import solver
from solver.mesh.io import load_mesh_file
from solver.shape_space import MAX_SHAPES
from tests.cli.test_cli_commands import run_both
from tests.helpers.gltf_validator import validate_gltf
from tests.helpers.poses import bent_pose
from tests.helpers.service import rigid_error
from tests.service.test_gltf_animation import accessor, read_glb


def poses(workdir):
    V, F = load_mesh_file(workdir / "decimated-knight.off")
    P, Q = bent_pose(V, F, 0.5), bent_pose(V, F, -0.4, bend_axis=0)
    for name, X in (("p.obj", P), ("q.obj", Q)):
        (workdir / name).write_bytes(solver.mesh.io.save_mesh(X, F, "obj"))
    return V, P, Q, F


def test_blend_of_three_with_weights_as_animation_and_per_row(ffs, server, workdir):
    V, P, Q, F = poses(workdir)
    weights = [[1.0, 0.0, 0.0], [0.4, 0.3, 0.3], [0.0, 0.0, 1.0]]
    (workdir / "w.json").write_text(json.dumps(weights))
    inputs = ["decimated-knight.off", "p.obj", "q.obj"]
    local, remote = run_both(ffs, server, workdir, "blend", inputs, "anim.glb",
                             "--weights", "w.json")
    truth = solver.blend([V, P, Q], weights, F).vertices
    for path in (local, remote):
        data = path.read_bytes()
        assert validate_gltf(data, "glb")["issues"]["numErrors"] == 0
        doc, binary = read_glb(data)
        primitive = doc["meshes"][0]["primitives"][0]
        base = accessor(doc, binary, primitive["attributes"]["POSITION"])
        rows = [base + accessor(doc, binary, t["POSITION"]) for t in primitive["targets"]]
        assert np.abs(np.array(rows) - truth).max() < 1e-5
    local, remote = run_both(ffs, server, workdir, "blend", inputs, "row-{index}.obj",
                             "--weights", "w.json")
    for k in range(3):
        W = load_mesh_file(local.with_name(f"row-{k}.obj"))[0]
        assert np.abs(W - truth[k]).max() < 1e-9
        assert np.abs(load_mesh_file(remote.with_name(f"row-{k}.obj"))[0] - W).max() < 1e-9


def test_blend_t_into_one_json_and_bad_weights(ffs, server, workdir):
    V, P, _, F = poses(workdir)
    done = ffs("blend", "decimated-knight.off", "p.obj", "-t", "0", "1.5", "-o", "rows.json")
    assert done.returncode == 0, done.stderr
    doc = json.loads((workdir / "rows.json").read_text())
    np.testing.assert_allclose(doc["vertices"], solver.interpolate(V, P, F, [0.0, 1.5]),
                               atol=1e-9)
    (workdir / "w.json").write_text("[[0.5, 0.5]]")
    bad = ffs("blend", "decimated-knight.off", "p.obj", "q.obj", "--weights", "w.json",
              "-o", "x.obj")
    assert bad.returncode == 2 and "rows of 3 weights" in bad.stderr
    three = ffs("blend", "decimated-knight.off", "p.obj", "q.obj", "-t", "0.5", "-o", "x.obj")
    assert three.returncode == 2 and "--weights" in three.stderr
    (workdir / "w.json").write_text("[[0.5, 0.6]]")
    off = ffs("blend", "decimated-knight.off", "p.obj", "--weights", "w.json", "-o", "x.obj")
    assert off.returncode == 1 and "weights" in off.stderr + off.stdout
    # one mesh: -t blends two (newcomer sweep: it said "1 meshes need --weights (rows of 1
    # weights)"); a blend takes 1 to MAX_SHAPES meshes, as the library and /v1/blend do
    one = ffs("blend", "decimated-knight.off", "-t", "0.5", "-o", "x.obj")
    assert one.returncode == 2 and "-t blends two meshes (A B), got 1" in one.stderr, one.stderr
    assert "one mesh takes --weights (rows of 1 weight)" in one.stderr
    assert "1 meshes" not in one.stderr
    (workdir / "w1.json").write_text("[[1.0]]")
    for where in ((), ("--server", server)):
        alone = ffs("blend", "decimated-knight.off", "--weights", "w1.json", "-o", "one.obj",
                    "--no-refine", *where)
        assert alone.returncode == 0, alone.stderr
        got = trimesh.load(workdir / "one.obj", process=False).vertices
        np.testing.assert_allclose(got, solver.blend([V], [[1.0]], F, refine=False).vertices[0],
                                   atol=1e-9)
    many = [f"k{k}.obj" for k in range(MAX_SHAPES + 1)]
    for name in many:
        shutil.copy(workdir / "p.obj", workdir / name)
    (workdir / "w65.json").write_text(json.dumps([[1.0] + [0.0] * MAX_SHAPES]))
    for command, extra in (("blend", ("--weights", "w65.json")), ("mean", ())):
        run = ffs(command, *many, *extra, "-o", "x.obj")
        assert run.returncode == 2, run.stderr  # before any work, as other usage errors
        assert f"{command} takes 1 to {MAX_SHAPES} meshes with the same faces; got 65" in (
            run.stderr), run.stderr


def test_mean_and_transfer(ffs, server, workdir):
    V, P, Q, F = poses(workdir)
    local, remote = run_both(ffs, server, workdir, "mean",
                             ["decimated-knight.off", "p.obj", "q.obj"], "mean.obj")
    truth = solver.mean([V, P, Q], F)
    for path in (local, remote):
        assert np.abs(load_mesh_file(path)[0] - truth).max() < 1e-9
    local, remote = run_both(ffs, server, workdir, "transfer",
                             ["decimated-knight.off", "p.obj", "decimated-knight.off"],
                             "moved.obj")
    for path in (local, remote):
        assert rigid_error(load_mesh_file(path)[0], P) < 1e-8


def test_blend_rows_past_the_thresholds_warn_and_strict_exits_1(ffs, server, workdir):
    """A blend of a mesh and its copy stretched 3x along z leaves a dihedral error past the
    documented limit in the middle row: WARN in the summary, the row named on stderr, exit
    1 with --strict; locally and on the service, with the library's warning."""
    V, _, _, F = poses(workdir)
    (workdir / "tall.obj").write_bytes(solver.mesh.io.save_mesh(V * [1.0, 1.0, 3.0], F, "obj"))
    (workdir / "w.json").write_text("[[1.0, 0.0], [0.5, 0.5]]")
    truth = solver.blend([V, V * [1.0, 1.0, 3.0]], [[1.0, 0.0], [0.5, 0.5]], F).warnings
    assert {w["code"] for w in truth} >= {"angle-error"} and {w["row"] for w in truth} == {1}
    for where in ([], ["--server", server]):
        run = ffs("blend", "decimated-knight.off", "tall.obj", "--weights", "w.json",
                  "-o", "rows.json", *where)
        assert run.returncode == 0, run.stderr
        assert "WARN angle-error" in run.stdout, run.stdout
        angle = {w["code"]: w for w in truth}["angle-error"]
        assert f"warning: row 1: {angle['message']}" in run.stderr, run.stderr
        strict = ffs("blend", "decimated-knight.off", "tall.obj", "--weights", "w.json",
                     "-o", "rows.json", "--strict", *where)
        assert strict.returncode == 1, strict.stdout + strict.stderr
