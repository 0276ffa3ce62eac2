"""``ffs vjp``: a cotangent of the reconstructed vertices pulled back to the forms, in-process
and with ``--server`` (a real uvicorn), against the library's cotangents
(:func:`solver.reconstruct_vjp`) on bent forms (linear and refined), one cotangent and a
batch, .npy and .json cotangents, .npz and .json outputs; and its usage errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

import solver
from solver.mesh.io import load_mesh_file, save_mesh
from tests.helpers.real_meshes import CASES as REAL
from tests.helpers.welded_meshes import CASES as WELDED


def bent_forms(workdir, name: str, factor: float) -> solver.Forms:
    V, F = load_mesh_file(workdir / name)
    forms = solver.fundamental_forms(V, F)
    bent = solver.Forms(forms.faces, forms.edges, forms.lengths, factor * forms.angles)
    np.savez(workdir / "bent.npz", faces=bent.faces, edges=bent.edges, lengths=bent.lengths,
             angles=bent.angles)
    return bent


def read_result(path):
    if path.suffix == ".npz":
        return dict(np.load(path))
    return {k: np.asarray(v) for k, v in json.loads(path.read_text()).items()
            if k != "report"}


@pytest.mark.parametrize(("name", "factor", "refine", "k", "output"), [
    ("decimated-knight.off", 0.9, "--no-refine", 1, "grads.npz"),
    ("decimated-knight.off", 0.9, "--refine", 2, "grads.json"),
    ("torus.off", 0.95, "--no-refine", 3, "grads.json"),
])
def test_vjp_gives_the_librarys_cotangents(ffs, server, workdir, name, factor, refine, k,
                                           output):
    forms = bent_forms(workdir, name, factor)
    n = int(forms.faces.max()) + 1
    rng = np.random.default_rng(k)
    G = rng.standard_normal((n, 3)) if k == 1 else rng.standard_normal((k, n, 3))
    if k == 2:
        (workdir / "g.json").write_text(json.dumps({"cotangent": G.tolist()}))
        cotangent = "g.json"
    else:
        np.save(workdir / "g.npy", G)
        cotangent = "g.npy"
    result, vjp = solver.reconstruct_vjp(forms.faces, forms.edges, forms.lengths,
                                         forms.angles, refine=refine == "--refine")
    truth = vjp.cotangents(G)
    scale = max(np.abs(truth.lengths).max(), np.abs(truth.angles).max())
    tolerance = 1e-9 if refine == "--no-refine" else 1e-6  # refined: other BLAS threads
    for where in (["--threads", "1"], ["--server", server]):
        done = ffs("vjp", "bent.npz", "--cotangent", cotangent, refine, "-o", output, *where)
        assert done.returncode == 0, done.stderr
        got = read_result(workdir / output)
        np.testing.assert_allclose(got["grad_lengths"], truth.lengths, atol=tolerance * scale)
        np.testing.assert_allclose(got["grad_angles"], truth.angles, atol=tolerance * scale)
        np.testing.assert_allclose(got["vertices"], result.vertices, atol=tolerance * 10)
        np.testing.assert_array_equal(got["faces"], forms.faces)
        assert got["grad_lengths"].shape == truth.lengths.shape


def test_vjp_usage_and_file_errors(ffs, workdir):
    bent_forms(workdir, "face.off", 0.9)
    missing = ffs("vjp", "bent.npz", "-o", "g.npz")
    assert missing.returncode == 2 and "--cotangent" in missing.stderr
    wrong_format = ffs("vjp", "bent.npz", "--cotangent", "g.npy", "-o", "g.obj")
    assert wrong_format.returncode == 2 and "json, npz" in wrong_format.stderr
    np.save(workdir / "g.npy", np.zeros((4, 2)))
    bad_shape = ffs("vjp", "bent.npz", "--cotangent", "g.npy", "-o", "g.npz")
    assert bad_shape.returncode == 2 and "--cotangent" in bad_shape.stderr  # read up front
    assert "(n, 3)" in bad_shape.stderr and "Traceback" not in bad_shape.stderr
    np.save(workdir / "g.npy", np.zeros((4, 3)))  # the wrong vertex count: the solver's check
    too_few = ffs("vjp", "bent.npz", "--cotangent", "g.npy", "-o", "g.npz")
    assert too_few.returncode == 1 and "cotangent" in too_few.stderr
    assert "Traceback" not in too_few.stderr


@pytest.mark.parametrize("name", ["cones-at-apex", "duplicated-corner"])
def test_vjp_of_a_real_file(ffs, server, workdir, name):
    """``ffs vjp`` of a non-manifold or welded mesh file (its own forms: vertex_map,
    weld_map, placement): per file vertex, on the file's faces, the library's cotangents,
    in-process and on a server."""
    V, F = REAL[name]() if name in REAL else WELDED[name]()[:2]
    (workdir / "real.off").write_bytes(save_mesh(V, F, "off"))
    G = np.random.default_rng(2).standard_normal(V.shape)
    np.save(workdir / "g.npy", G)
    forms = solver.fundamental_forms(V, F)
    assert forms.vertex_map is not None
    result, vjp = solver.reconstruct_vjp(
        forms.faces, forms.edges, forms.lengths, forms.angles, refine=False,
        vertex_map=forms.vertex_map, weld_map=forms.weld_map, placement=forms.placement,
        n_vertices=len(V))
    truth = vjp.cotangents(G)
    scale = max(np.abs(truth.lengths).max(), np.abs(truth.angles).max())
    for where in (["--threads", "1"], ["--server", server]):
        done = ffs("vjp", "real.off", "--cotangent", "g.npy", "--no-refine", "-o", "g.npz",
                   *where)
        assert done.returncode == 0, done.stderr
        got = read_result(workdir / "g.npz")
        np.testing.assert_allclose(got["grad_lengths"], truth.lengths, atol=1e-9 * scale)
        np.testing.assert_allclose(got["grad_angles"], truth.angles, atol=1e-9 * scale)
        np.testing.assert_allclose(got["vertices"], result.vertices, atol=1e-8)
        np.testing.assert_array_equal(got["faces"], forms.vertex_map[forms.faces])
