"""Vertices joined by zero-length edges through ``ffs`` (issue 40, solver.mesh.weld),
in-process and with ``--server``: forms (.json and .npz keep ``weld_map``) -> reconstruct
gives the file's mesh back (one rigid alignment), deform hits its handles, and ``ffs forms``
says how many vertices it welded and faces it dropped."""

from __future__ import annotations

import json

import pytest

from solver.mesh.io import load_mesh_file, save_mesh
from tests.helpers.cli import deform_by_three_handles, where
from tests.helpers.meshes import rigid_alignment_error
from tests.helpers.welded_meshes import CASES

NAMES = ["latlong-sphere", "duplicated-corner", "repeated-index-face", "torus-near-pairs"]


@pytest.mark.parametrize("remote", [False, True], ids=["local", "server"])
@pytest.mark.parametrize("name", NAMES)
def test_forms_reconstruct_deform(ffs, server, workdir, name, remote):
    V, F, welded, dropped = CASES[name]()
    (workdir / f"{name}.off").write_bytes(save_mesh(V, F, "off"))
    for fmt in ("json", "npz"):
        done = ffs("forms", f"{name}.off", "-o", f"{name}.{fmt}", *where(server, remote))
        assert done.returncode == 0, done.stderr
        assert f"{welded} vertices welded, {dropped} faces dropped" in done.stdout + done.stderr
        done = ffs("reconstruct", f"{name}.{fmt}", "-o", f"{name}-{fmt}.ply", "-q",
                   *where(server, remote))
        assert done.returncode == 0, done.stderr
        rebuilt, _ = load_mesh_file(workdir / f"{name}-{fmt}.ply")
        assert rebuilt.shape == V.shape
        assert rigid_alignment_error(rebuilt, V) < 1e-8, (name, fmt)
    doc = json.loads((workdir / f"{name}.json").read_text())
    assert len(doc["dropped_faces"]) == dropped
    deform_by_three_handles(ffs, workdir, name, V, F, where(server, remote))
