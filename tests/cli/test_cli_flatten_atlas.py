"""``ffs flatten`` on closed, genus-2, multi-part and holed meshes (issue 41): OBJ with
``vt`` / ``f v/vt`` read back by trimesh, GLB with TEXCOORD_0 valid for the Khronos
validator, the same atlas in-process and on a server, no flips, no overlap (PIL)."""

from __future__ import annotations

import re

import numpy as np
import pytest

import solver
from solver.mesh.packing import signed_areas
from tests.cli.test_cli_commands import run_both
from tests.helpers.atlas import genus_two, overlapping_pixels
from tests.helpers.gltf_validator import validate_gltf
from tests.helpers.meshes import holed, load


def _obj_atlas(path):
    """(v (n, 3), vt (k, 2), f (m, 3), f_vt (m, 3)) parsed from OBJ text (not the solver's
    reader)."""
    text = path.read_text()
    v = np.array([line.split()[1:] for line in text.splitlines() if line.startswith("v ")],
                 dtype=float)
    vt = np.array([line.split()[1:] for line in text.splitlines() if line.startswith("vt ")],
                  dtype=float)
    corners = np.array([re.findall(r"(\d+)/(\d+)", line) for line in text.splitlines()
                        if line.startswith("f ")], dtype=int)
    return v, vt, corners[:, :, 0] - 1, corners[:, :, 1] - 1


@pytest.mark.parametrize("name, make", [
    ("torus", lambda: load("torus.off")),
    ("genus2", genus_two),
    ("octopus-holes", lambda: holed(*load("octopus-low-surface.off"), [5, 100, 300])),
    ("face-scan-holes", lambda: holed(*load("face.off"), [300, 600, 900])),
])
def test_flatten_writes_uv_obj_and_glb(ffs, server, workdir, name, make):
    V, F = make()
    (workdir / f"{name}.obj").write_bytes(solver.mesh.io.save_mesh(V, F, "obj"))
    local, remote = run_both(ffs, server, workdir, "flatten", [f"{name}.obj"], "out.obj")
    v, vt, f, f_vt = _obj_atlas(local)
    np.testing.assert_allclose(v, V, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(f, F)
    atlas = solver.parameterize(V, F)    # the library's atlas, computed once (5 s on octopus)
    charts = atlas.report.atlas["charts"]
    assert (len(vt) > len(V)) == (charts > 1)    # seam vertices: one vt per chart
    assert (vt >= 0).all() and (vt <= 1).all()
    assert (signed_areas(vt, f_vt) > 0).all()
    chart = np.asarray(atlas.face_chart)
    assert name == "face-scan-holes" or charts >= 2
    assert overlapping_pixels(vt, f_vt, chart) == 0
    _, vt_remote, _, f_vt_remote = _obj_atlas(remote)
    np.testing.assert_array_equal(f_vt_remote, f_vt)
    np.testing.assert_allclose(vt_remote, vt, atol=1e-6)

    local, _ = run_both(ffs, server, workdir, "flatten", [f"{name}.obj"], "out.glb")
    report = validate_gltf(local.read_bytes(), "glb")
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    assert report["info"]["totalVertexCount"] == len(vt)
    assert "TEXCOORD_0" in local.read_bytes()[:4096].decode("latin-1")


def test_multi_part_model_and_npz_arrays(ffs, server, workdir):
    parts = [load("torus.off"), load("decimated-knight.off"), load("face.off")]
    vertices, faces, offset = [], [], 0
    for k, (V, F) in enumerate(parts):
        vertices.append((V - V.min(axis=0)) / np.ptp(V, axis=0).max() + [1.5 * k, 0, 0])
        faces.append(F + offset)
        offset += len(V)
    V, F = np.concatenate(vertices), np.concatenate(faces)
    (workdir / "parts.obj").write_bytes(solver.mesh.io.save_mesh(V, F, "obj"))
    local, remote = run_both(ffs, server, workdir, "flatten", ["parts.obj"], "parts.npz")
    for path in (local, remote):
        arrays = np.load(path)
        assert np.array_equal(arrays["uv_vertex"][arrays["uv_faces"]], F)
        assert len(arrays["flipped_faces"]) == 0
        assert (signed_areas(arrays["texcoords"], arrays["uv_faces"]) > 0).all()
        assert overlapping_pixels(arrays["texcoords"], arrays["uv_faces"],
                                  arrays["face_chart"]) == 0
        # every part has charts of its own: no chart spans two parts
        part = np.repeat(np.arange(3), [len(p[1]) for p in parts])
        for c in np.unique(arrays["face_chart"]):
            assert len(np.unique(part[arrays["face_chart"] == c])) == 1
