"""``Client.reconstruct_vjp`` (``POST /v1/reconstruct/vjp`` on a real uvicorn) and
``Local.reconstruct_vjp`` (in-process) against the library's cotangents
(:func:`solver.reconstruct_vjp`), on forms that integrate and on noisy ones, linear and
refined, one cotangent and a batch, with position constraints."""

from __future__ import annotations

import numpy as np
import pytest

import ffs
import solver
from ffs.local import Local
from tests.helpers.meshes import load
from tests.helpers.real_meshes import CASES as REAL
from tests.helpers.welded_meshes import CASES as WELDED


def noisy(name: str, noise: float, seed: int) -> tuple[np.ndarray, solver.Forms]:
    V, F = load(name)
    forms = solver.fundamental_forms(V, F)
    rng = np.random.default_rng(seed)
    angles = np.clip(forms.angles + noise * rng.standard_normal(len(forms.angles)),
                     -np.pi + 1e-6, np.pi)
    return V, solver.Forms(forms.faces, forms.edges, forms.lengths, angles)


CASES = [("decimated-knight.off", 0.01, False, 1), ("decimated-knight.off", 0.01, None, 2),
         ("face.off", 0.0, False, 1), ("torus.off", 0.005, None, 1)]
"""mesh, angle noise (rad), refine, cotangents at once."""


def truth(forms: solver.Forms, G: np.ndarray, refine: bool | None, constraints=None):
    result, vjp = solver.reconstruct_vjp(forms.faces, forms.edges, forms.lengths,
                                         forms.angles, refine=refine,
                                         constraints=constraints)
    return result, vjp.cotangents(G)


def assert_matches(got: ffs.results.VjpResult, result, expected, rtol: float) -> None:
    scale = max(np.abs(expected.lengths).max(), np.abs(expected.angles).max())
    np.testing.assert_allclose(got.vertices, result.vertices, atol=rtol * 10)
    np.testing.assert_allclose(got.grad_lengths, expected.lengths, atol=rtol * scale)
    np.testing.assert_allclose(got.grad_angles, expected.angles, atol=rtol * scale)
    for name in ("positions", "frames"):
        want = getattr(expected, name)
        np.testing.assert_allclose(getattr(got, f"grad_{name}"), want,
                                   atol=rtol * max(1.0, np.abs(want).max(initial=0)))
    assert got.grad_lengths.shape == expected.lengths.shape


@pytest.mark.parametrize(("name", "noise", "refine", "k"), CASES)
def test_client_and_local_match_the_library(server, name, noise, refine, k):
    V, forms = noisy(name, noise, seed=len(name))
    rng = np.random.default_rng(k)
    G = rng.standard_normal((len(V), 3)) if k == 1 else rng.standard_normal((k, len(V), 3))
    result, expected = truth(forms, G, refine)
    client_forms = ffs.Forms(forms.faces, forms.edges, forms.lengths, forms.angles)
    with ffs.Client(server, timeout=300) as client:
        remote = client.reconstruct_vjp(client_forms, cotangent=G, refine=refine)
    local = Local().reconstruct_vjp(client_forms, cotangent=G, refine=refine)
    # refined answers: other BLAS thread counts change their round-off
    assert_matches(remote, result, expected, 1e-9 if refine is False else 1e-6)
    assert_matches(local, result, expected, 1e-9 if refine is False else 1e-6)
    mode = "linear" if refine is False else "refined"
    assert remote.report["vjp"]["mode"] == local.report["vjp"]["mode"] == mode


def test_constraint_targets_and_a_job(server):
    V, forms = noisy("decimated-knight.off", 0.01, seed=3)
    pins = [0, len(V) // 2, len(V) - 1]
    free = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                              refine=False)  # a frame that fixes the gauge: face 5's
    U, _, Vt = np.linalg.svd(free.frames[5])  # its nearest rotation
    frame = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    constraints = {"positions": [{"vertex": v, "position": V[v].tolist(), "weight": 10.0}
                                 for v in pins],
                   "frames": [{"face": 5, "frame": frame.tolist()}]}
    G = np.random.default_rng(4).standard_normal((len(V), 3))
    result, expected = truth(forms, G, False, solver.Constraints.from_records(
        constraints["positions"], constraints["frames"]))
    assert expected.positions.shape == (3, 3) and expected.frames.shape == (1, 3, 3)
    stages = []
    with ffs.Client(server, timeout=300) as client:  # progress: runs as a job
        remote = client.reconstruct_vjp(forms.faces, forms.edges, forms.lengths, forms.angles,
                                        cotangent=G, constraints=constraints, refine=False,
                                        progress=lambda stage, f: stages.append(stage))
        job = client.submit("reconstruct/vjp", forms.faces, forms.edges, forms.lengths,
                            forms.angles, cotangent=G, constraints=constraints, refine=False)
        queued = job.result(timeout=300)
        job.discard()
    local = Local().reconstruct_vjp(forms.faces, forms.edges, forms.lengths, forms.angles,
                                    cotangent=G, constraints=constraints, refine=False)
    for got in (remote, queued, local):
        assert_matches(got, result, expected, 1e-9)
    # Progress is sampled by polling the job: which stages are seen depends on timing.
    assert stages and set(stages) <= {"validate", "assemble", "factorize", "solve", "refine",
                                      "adjoint", "encode"}, stages


def test_bad_cotangent_is_the_same_error_here_and_there(server):
    V, forms = noisy("face.off", 0.0, seed=0)
    bad = np.zeros((len(V) - 1, 3))
    with ffs.Client(server) as client, pytest.raises(ffs.InvalidInputError) as remote:
        client.reconstruct_vjp(forms.faces, forms.edges, forms.lengths, forms.angles,
                               cotangent=bad)
    with pytest.raises(solver.core.errors.SolverInputError) as local:
        Local().reconstruct_vjp(forms.faces, forms.edges, forms.lengths, forms.angles,
                                cotangent=bad)
    assert remote.value.pointer.endswith("cotangent") or "cotangent" in str(remote.value)
    assert local.value.field == "cotangent"


@pytest.mark.parametrize(("name", "refine"), [("cones-at-apex", False),
                                              ("edge-with-3-faces", None),
                                              ("duplicated-corner", False)])
def test_a_real_files_forms_here_and_there(server, name, refine):
    """The forms of a non-manifold or welded file (``fundamental_forms``: vertex_map,
    weld_map, placement) through Client and Local: per file vertex, on the file's faces,
    the library's gradients."""
    V, F = REAL[name]() if name in REAL else WELDED[name]()[:2]
    G = np.random.default_rng(5).standard_normal((len(V), 3))
    with ffs.Client(server, timeout=300) as client:
        forms = client.fundamental_forms(V, F)
        assert forms.vertex_map is not None
        remote = client.reconstruct_vjp(forms, cotangent=G, refine=refine)
        mesh = client.reconstruct(forms, refine=refine)
    local = Local().reconstruct_vjp(forms, cotangent=G, refine=refine)
    result, vjp = solver.reconstruct_vjp(
        forms.faces, forms.edges, forms.lengths, forms.angles, refine=refine,
        vertex_map=forms.vertex_map, weld_map=forms.weld_map, placement=forms.placement)
    expected = vjp.cotangents(G)
    for got in (remote, local):
        assert_matches(got, result, expected, 1e-9 if refine is False else 1e-6)
        np.testing.assert_array_equal(got.faces, mesh.faces)
        assert got.vertices.shape == V.shape


def test_progress_names_stages_never_a_status():
    """Between a job's start and its first progress event the service says ``running`` with
    no stage; the client's progress callback then gets nothing (it once got ``running``, not a
    stage name, which the test above caught under load). A queued job is ``queued``; a stage,
    with its fraction."""
    from ffs.jobs import JobProgress, _report

    seen = []
    for state in (JobProgress("queued", None, 0.0, {}), JobProgress("running", None, 0.0, {}),
                  JobProgress("running", "solve", 0.2, {"solve": 0.5}),
                  JobProgress("succeeded", None, 1.0, {})):
        _report(state, lambda stage, fraction: seen.append((stage, fraction)))
    assert seen == [("queued", 0.0), ("solve", 0.5)]
