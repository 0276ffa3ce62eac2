"""ffs.Client's shape-space methods against a real uvicorn: blend (binary and JSON bodies,
as a job with per-row progress), blend_gltf, mean, transfer, submit, and a bad row as a
typed exception naming it; each against the library."""

from __future__ import annotations

import numpy as np
import pytest

import ffs
import solver
from solver.mesh.io import save_mesh
from tests.helpers.gltf_validator import validate_gltf
from tests.helpers.meshes import load
from tests.helpers.poses import bent_pose


@pytest.fixture(scope="module")
def poses():
    V, F = load("decimated-knight.off")
    return V, bent_pose(V, F, 0.5), bent_pose(V, F, -0.4, bend_axis=0), F


def test_blend_mean_transfer_match_the_library(server, poses):
    V, P, Q, F = poses
    weights = [[0.2, 0.5, 0.3], [-0.2, 0.6, 0.6]]
    truth = solver.blend([V, P, Q], weights, F).vertices
    for binary in (True, False):
        with ffs.Client(server, binary=binary) as client:
            rows = client.blend([V, P, Q], F, weights)
            np.testing.assert_allclose(rows.vertices, truth, atol=1e-9)
            assert rows.weights.tolist() == weights and len(rows.reports) == 2
    with ffs.Client(server) as client:
        np.testing.assert_allclose(client.blend([V, P], F, t=[0.0, 1.5]).vertices,
                                   solver.interpolate(V, P, F, [0.0, 1.5]), atol=1e-9)
        np.testing.assert_allclose(client.mean([V, P, Q], F).vertices,
                                   solver.mean([V, P, Q], F), atol=1e-9)
        np.testing.assert_allclose(client.transfer(V, P, Q, F).vertices,
                                   solver.transfer(V, P, Q, F), atol=1e-9)
        glb = client.blend_gltf([V, P], F, t=[0.0, 0.5, 1.0], times=[0.0, 1.0, 2.0])
        report = validate_gltf(glb, "glb")
        assert report["issues"]["numErrors"] == 0 and report["info"]["animationCount"] == 1


def test_blend_as_a_job_reports_rows_and_bad_rows_raise(server, poses):
    V, P, _, F = poses
    t = np.linspace(0.0, 1.0, 30)
    with ffs.Client(server) as client:
        seen: list[tuple[str, float]] = []
        rows = client.blend([V, P], F, t=t, progress=lambda stage, f: seen.append((stage, f)))
        assert rows.vertices.shape == (30, len(V), 3)
        fractions = [f for stage, f in seen if stage == "rows"]
        assert fractions == sorted(fractions) and any(0 < f < 1 for f in fractions), seen
        assert seen[-1] == ("encode", 1.0)
        job = client.submit("blend", [V, P], F, [[0.5, 0.5]])
        assert job.result(timeout=120).vertices.shape == (1, len(V), 3)
        job.discard()
        with pytest.raises(ffs.InvalidInputError) as error:
            client.blend([V, P], F, [[0.5, 0.5], [0.7, 0.7]])
        assert "weights" in str(error.value) and "1.4" in str(error.value)


def test_blend_of_k_uploaded_files_and_its_row_warnings(server, poses, tmp_path):
    """blend_files uploads the files as they are (three formats), answers as the library
    does, and exposes each row's warnings with its row (a blend with a copy stretched 3x
    along z leaves a dihedral error past the limit; the given shape itself none)."""
    V, P, Q, F = poses
    paths = []
    for name, X in (("a.off", V), ("b.obj", P), ("c.ply", Q)):
        (tmp_path / name).write_bytes(save_mesh(X, F, name[-3:]))
        paths.append(tmp_path / name)
    weights = [[0.2, 0.5, 0.3], [-0.2, 0.6, 0.6]]
    with ffs.Client(server) as client:
        rows = client.blend_files(paths, weights)
        np.testing.assert_allclose(rows.vertices, solver.blend([V, P, Q], weights, F).vertices,
                                   atol=1e-5)  # PLY holds float32
        assert rows.warnings == []
        (tmp_path / "tall.off").write_bytes(save_mesh(V * [1, 1, 3.0], F, "off"))
        rows = client.blend_files([paths[0], tmp_path / "tall.off"], [[0.5, 0.5], [0, 1]])
        truth = solver.blend([V, V * [1, 1, 3.0]], [[0.5, 0.5], [0, 1]], F).warnings
        assert [(w["row"], w["code"]) for w in rows.warnings] == [
            (w["row"], w["code"]) for w in truth]
        assert "angle-error" in {w["code"] for w in rows.warnings}
        assert {w["row"] for w in rows.warnings} == {0}


def test_blend_gltf_carries_the_warnings_locally_and_remotely(server, poses):
    """A blend past what a surface can make: the GLB's ``asset.extras.warnings`` are the
    JSON answer's warnings, from the service and from ``ffs``'s local backend alike."""
    from ffs.local import Local
    from tests.service.test_gltf_animation import read_glb

    V, _, _, F = poses
    tall = [V, V * [1, 1, 3.0]]
    want = solver.blend(tall, [[0.5, 0.5], [0.0, 1.0]], F).warnings
    assert want
    with ffs.Client(server) as client:
        remote = read_glb(client.blend_gltf(tall, F, t=[0.5, 1.0]))[0]["asset"]["extras"]
    local = read_glb(Local().blend_gltf(tall, F, t=[0.5, 1.0]))[0]["asset"]["extras"]
    for got in (remote["warnings"], local["warnings"]):
        assert [(w["code"], w["row"]) for w in got] == [(w["code"], w["row"]) for w in want]
        assert [w["value"] for w in got] == pytest.approx([w["value"] for w in want])
