"""Meshes as people have them through ``ffs`` (issue 40), in-process and with ``--server``:
forms -> reconstruct of non-manifold, multi-part, folded, closed and zero-area-face meshes gives
the file's
mesh back (one rigid alignment; .json and .npz forms keep the vertex map and placement),
deform hits its handles, flatten accepts the open ones, quads are triangulated."""

from __future__ import annotations

import json

import numpy as np
import pytest

from solver.mesh.io import load_mesh_file, save_mesh
from tests.helpers.cli import deform_by_three_handles, where
from tests.helpers.meshes import rigid_alignment_error
from tests.helpers.real_meshes import CASES, HAS_CLOSED_PART

NAMES = ["edge-with-3-faces", "edge-with-4-faces", "cones-at-apex", "multi-component",
         "fin-at-pi", "closed-genus-2", "slivers-1e-4", "zero-area-inserted",
         "zero-area-open"]


@pytest.mark.parametrize("remote", [False, True], ids=["local", "server"])
@pytest.mark.parametrize("name", NAMES)
def test_forms_reconstruct_round_trip(ffs, server, workdir, name, remote):
    V, F = CASES[name]()
    (workdir / f"{name}.off").write_bytes(save_mesh(V, F, "off"))
    for fmt in ("json", "npz"):
        done = ffs("forms", f"{name}.off", "-o", f"{name}.{fmt}", "-q",
                   *where(server, remote))
        assert done.returncode == 0, done.stderr
        done = ffs("reconstruct", f"{name}.{fmt}", "-o", f"{name}-{fmt}.ply", "-q",
                   *where(server, remote))
        assert done.returncode == 0, done.stderr
        rebuilt, faces = load_mesh_file(workdir / f"{name}-{fmt}.ply")
        assert rebuilt.shape == V.shape and (faces == F).all()
        assert rigid_alignment_error(rebuilt, V) < 1e-8, (name, fmt)
    if name in {"edge-with-3-faces", "edge-with-4-faces", "cones-at-apex"}:
        assert "vertex_map" in json.loads((workdir / f"{name}.json").read_text())


@pytest.mark.parametrize("remote", [False, True], ids=["local", "server"])
@pytest.mark.parametrize("name", NAMES)
def test_deform_hits_its_handles(ffs, server, workdir, name, remote):
    V, F = CASES[name]()
    (workdir / f"{name}.off").write_bytes(save_mesh(V, F, "off"))
    _, faces = deform_by_three_handles(ffs, workdir, name, V, F, where(server, remote))
    assert (faces == F).all()


@pytest.mark.parametrize("name", [n for n in NAMES if n not in HAS_CLOSED_PART])
def test_flatten_accepts_them(ffs, server, workdir, name):
    V, F = CASES[name]()
    (workdir / f"{name}.obj").write_bytes(save_mesh(V, F, "obj"))
    for remote in (False, True):
        done = ffs("flatten", f"{name}.obj", "-o", f"{name}-flat.npz", "-q", *where(server, remote))
        assert done.returncode == 0, done.stderr
        with np.load(workdir / f"{name}-flat.npz") as flat:
            assert flat["uv"].shape == (len(V), 2)


def test_quads_in_an_off_file(ffs, server, workdir):
    (workdir / "quads.off").write_bytes(
        b"OFF\n6 2 0\n0 0 0\n1 0 0\n1 1 0.2\n0 1 0\n2 0 0.1\n2 1 0.3\n"
        b"4 0 1 2 3\n4 1 4 5 2\n")
    for remote in (False, True):
        done = ffs("forms", "quads.off", "-o", "quads.json", "-q", *where(server, remote))
        assert done.returncode == 0, done.stderr
        faces = json.loads((workdir / "quads.json").read_text())["faces"]
        assert faces == [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]]


@pytest.mark.parametrize("remote", [False, True], ids=["local", "server"])
def test_a_gltf_beside_its_buffer_file_is_read(ffs, server, workdir, remote):
    """A .gltf whose buffer is a separate file (as exporters write it) is read with the file
    beside it, in-process and with --server (the command line reads the mesh itself)."""
    import base64

    from solver.mesh.gltf import encode_gltf_json

    V, F = CASES["multi-component"]()
    doc = json.loads(encode_gltf_json(V, F))
    (workdir / "parts.bin").write_bytes(base64.b64decode(doc["buffers"][0]["uri"].split(",")[1]))
    doc["buffers"][0]["uri"] = "parts.bin"
    (workdir / "parts.gltf").write_text(json.dumps(doc))
    done = ffs("forms", "parts.gltf", "-o", "parts.json", "-q", *where(server, remote))
    assert done.returncode == 0, done.stderr
    done = ffs("reconstruct", "parts.json", "-o", "parts.ply", "-q", *where(server, remote))
    assert done.returncode == 0, done.stderr
    rebuilt, faces = load_mesh_file(workdir / "parts.ply")
    assert rebuilt.shape == V.shape and (faces == F).all()
    assert rigid_alignment_error(rebuilt, V.astype(np.float32).astype(np.float64)) < 1e-6
    (workdir / "parts.bin").unlink()
    done = ffs("forms", "parts.gltf", "-o", "parts.json", "-q", *where(server, remote))
    assert done.returncode != 0 and "cannot read its file 'parts.bin'" in done.stderr
