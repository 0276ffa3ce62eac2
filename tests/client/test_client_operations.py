"""The Python client against a real uvicorn: every operation against the library, binary
and JSON bodies alike, jobs with progress and cancellation, a session over the WebSocket and
over HTTP, problem documents as typed exceptions, a 503 retried, a timeout, and an import
without FastAPI."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

import ffs
import solver
from tests.helpers import REPO
from tests.helpers.meshes import load
from tests.helpers.service import metric_value, rigid_error


@pytest.fixture(scope="module")
def knight() -> tuple[np.ndarray, np.ndarray]:
    return load("decimated-knight.off")


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "json"])
def test_every_operation_matches_the_library(server, knight, binary):
    V, F = knight
    face = load("face.off")
    with ffs.Client(server, binary=binary) as client:
        forms = client.fundamental_forms(V, F)
        truth = solver.fundamental_forms(V, F)
        for name in ("faces", "edges", "lengths", "angles"):
            np.testing.assert_array_equal(getattr(forms, name), getattr(truth, name))
        assert forms.faces.dtype == np.int64 and forms.lengths.dtype == np.float64

        report = client.check_integrability(forms)
        assert report.integrable and report.max_defect < 1e-10
        assert report.vertex_defect.shape == (len(V),)
        bent = client.check_integrability(forms.faces, forms.edges, forms.lengths,
                                          0.8 * forms.angles, tol=1e-6)
        assert not bent.integrable and bent.report["tolerance"] == 1e-6

        mesh = client.reconstruct(forms)
        assert rigid_error(mesh.vertices, V) < 1e-9
        assert mesh.report["solve_path"] == "tree-integration"
        linear = client.reconstruct(forms.faces, forms.edges, forms.lengths, 0.8 * forms.angles,
                                    refine=False, orthonormalize=True)
        library = solver.reconstruct(forms.faces, forms.edges, forms.lengths,
                                     0.8 * forms.angles, refine=False, orthonormalize=True)
        np.testing.assert_allclose(linear.vertices, library.vertices, atol=1e-9)

        handles = [0, 100, 200]
        targets = V[handles] + [0.0, 0.0, 0.05]
        moved = client.deform(V, F, handles, targets, refine=False)
        np.testing.assert_allclose(moved.vertices,
                                   solver.deform(V, F, handles, targets, refine=False).vertices,
                                   atol=1e-9)
        np.testing.assert_array_equal(moved.faces, F)

        flat = client.parameterize(*face)
        np.testing.assert_allclose(flat.uv, solver.parameterize(*face).uv, atol=1e-6)
        assert len(flat.flipped_faces) == 0

        other = V + 0.05 * np.sin(4 * V[:, [1, 2, 0]])
        blend = client.interpolate(V, other, F, [0.0, 1.0])
        assert blend.vertices.shape == (2, len(V), 3) and blend.t == [0.0, 1.0]
        assert rigid_error(blend.vertices[0], V) < 1e-6
        single = client.interpolate(V, other, F, 0.5)
        assert single.vertices.shape == (len(V), 3) and single.refinement["refined"] in (True,
                                                                                          False)

        checked = client.mesh(V, F)
        np.testing.assert_array_equal(checked.vertices, V)
        assert checked.report["n_faces"] == len(F)
        uploaded = client.load_mesh(REPO / "tests" / "data" / "decimated-knight.off")
        np.testing.assert_array_equal(uploaded.vertices, V)


def test_binary_and_json_bodies_give_the_same_bits(server, knight):
    V, F = knight
    forms = solver.fundamental_forms(V, F)
    answers = []
    for binary in (True, False):
        with ffs.Client(server, binary=binary) as client:
            answers.append(client.reconstruct(forms.faces, forms.edges, forms.lengths,
                                              0.9 * forms.angles).vertices)
    np.testing.assert_array_equal(answers[0], answers[1])


def test_problem_documents_are_typed_exceptions_with_pointers(server, knight):
    V, F = knight
    bad = F.copy()
    bad[17, 1] = 9001
    with ffs.Client(server) as client:
        with pytest.raises(ffs.InvalidInputError) as caught:
            client.fundamental_forms(V, bad)
        error = caught.value
        assert error.status == 422 and error.type == "/problems/index-out-of-range"
        assert error.kind == "index-out-of-range" and error.title
        assert (error.field, error.index, error.pointer) == ("faces", 17, "/faces/17")
        assert "9001" in error.detail

        with pytest.raises(ffs.InvalidInputError) as caught:  # a schema error: its pointer
            client.deform(V, F, [0], [[0.0, 0.0, float("nan")]])
        assert caught.value.kind == "validation-error"
        assert caught.value.pointer == "/handles/0/position/2"

        with pytest.raises(ffs.NotFoundError) as caught:
            client.job("0123456789abcdef").status()
        assert caught.value.status == 404

        with pytest.raises(ffs.InvalidInputError) as caught:  # a failed job raises the same
            client.fundamental_forms(V, bad, progress=lambda stage, fraction: None)
        assert caught.value.pointer == "/faces/17"


def test_job_progress_result_and_cancel(server, knight):
    V, F = knight
    forms = solver.fundamental_forms(V, F)
    with ffs.Client(server) as client:
        seen: list[tuple[str, float]] = []
        refined = client.reconstruct(forms.faces, forms.edges, forms.lengths,
                                     0.9 * forms.angles, refine=True,
                                     progress=lambda stage, f: seen.append((stage, f)))
        direct = client.reconstruct(forms.faces, forms.edges, forms.lengths,
                                    0.9 * forms.angles, refine=True)
        np.testing.assert_array_equal(refined.vertices, direct.vertices)
        assert seen and seen[-1] == ("encode", 1.0)
        assert all(0.0 <= f <= 1.0 for _, f in seen)

        job = client.submit("parameterize", *load("face.off"))
        flat = job.result(timeout=120)
        assert flat.uv.shape == (1180, 2) and job.progress().status == "succeeded"
        job.discard()
        with pytest.raises(ffs.NotFoundError):
            job.status()

        rng = np.random.default_rng(0)
        noisy = V + 0.02 * rng.standard_normal(V.shape)
        slow = client.submit("interpolate", V, noisy, F, list(np.linspace(0, 1, 64)))
        deadline = time.monotonic() + 60
        while slow.progress().status == "queued" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert slow.progress().status == "running"
        slow.cancel()
        assert slow.progress().status == "cancelled"
        with pytest.raises(ffs.JobCancelledError):
            slow.result(timeout=10)


def test_session_over_websocket_and_over_http(server, knight):
    V, F = knight
    handles = [0, 100, 200]
    deformer = solver.Deformer(V, F, handles=handles)
    with ffs.Client(server) as client:
        for transport, tolerance in (("ws", 1e-5), ("http", 1e-9)):
            with client.session(V, F, handles, transport=transport) as session:
                assert session.transport == transport and session.handles == handles
                for lift in (0.05, 0.1):
                    targets = V[handles] + [0.0, 0.0, lift]
                    vertices = session.drag(targets)
                    expected = deformer.solve(targets)
                    scale = np.abs(expected).max()
                    assert np.abs(vertices - expected).max() <= tolerance * scale
                assert session.state()["solves"] == 2
                with pytest.raises(ffs.InvalidInputError):  # two targets for three handles
                    session.drag(V[handles[:2]])
            with pytest.raises((ffs.NotFoundError, ffs.GoneError)):
                session.state()
        with client.session(V, F, handles) as session:  # auto: the WebSocket
            assert session.transport == "ws"


def test_503_is_retried_after_retry_after(busy_server, knight):
    V, F = knight
    rng = np.random.default_rng(1)
    noisy = V + 0.02 * rng.standard_normal(V.shape)
    with ffs.Client(busy_server, max_wait=2.0, retries=20) as client:
        before = metric_value(httpx.get(f"{busy_server}/metrics").text,
                              "ffs_http_requests_total", status="503")
        blocker = client.submit("interpolate", V, noisy, F, list(np.linspace(0, 1, 64)))
        while blocker.progress().status == "queued":
            time.sleep(0.05)
        with httpx.Client(base_url=busy_server) as raw:  # the worker is busy: 503 now
            refused = raw.post("/v1/forms", json={"vertices": V.tolist(), "faces": F.tolist()})
            assert refused.status_code == 503 and int(refused.headers["retry-after"]) >= 1
        threading.Timer(1.5, blocker.cancel).start()
        started = time.monotonic()
        forms = client.fundamental_forms(V, F)  # retried until the worker is free
        assert time.monotonic() - started >= 1.0
        np.testing.assert_array_equal(forms.lengths, solver.fundamental_forms(V, F).lengths)
        after = metric_value(httpx.get(f"{busy_server}/metrics").text,
                             "ffs_http_requests_total", status="503")
        assert after - before >= 2  # the raw refusal and at least one of the client's


def test_timeout_raises_request_timeout(busy_server, knight):
    V, F = knight
    noisy = V + 0.02 * np.random.default_rng(2).standard_normal(V.shape)
    with ffs.Client(busy_server, timeout=0.3) as client:
        with pytest.raises(ffs.RequestTimeoutError):
            client.interpolate(V, noisy, F, list(np.linspace(0, 1, 64)))
        assert isinstance(ffs.RequestTimeoutError("x"), TimeoutError)


BLOCK_FASTAPI = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"fastapi", "starlette", "pydantic", "service", "uvicorn",
                                  "solver", "scipy", "trimesh", "orjson"}:
            raise ImportError(f"{name} is blocked")
sys.meta_path.insert(0, Block())
import numpy as np
from ffs import Client, InvalidInputError
V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
with Client(sys.argv[1]) as client:
    forms = client.fundamental_forms(V, F)
    mesh = client.reconstruct(forms)
    try:
        client.fundamental_forms(V, F + 1)
    except InvalidInputError as error:
        print(len(forms.edges), mesh.vertices.shape, error.pointer)
"""


def test_the_client_imports_without_fastapi_or_the_library(server):
    result = subprocess.run([sys.executable, "-c", BLOCK_FASTAPI, server], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split()[0] == "6" and "(4, 3)" in result.stdout
    assert "/faces/" in result.stdout


def test_reconstruct_takes_the_cut_and_placement_as_keywords(server):
    """The README's non-manifold call, ``reconstruct(faces, edges, lengths, angles,
    vertex_map=..., placement=...)``, works through the client as in the library (newcomer
    sweep: it was a 422 ``options.vertex_map``), and gives what the Forms alone gives."""
    from tests.helpers.meshes import icosphere, side_by_side

    fin = (np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1.0]]),
           np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))  # three faces on the edge 0-1
    V, F = side_by_side(fin, icosphere(1))
    with ffs.Client(server, timeout=60) as client:
        forms = client.fundamental_forms(V, F)
        assert forms.vertex_map is not None and forms.placement is not None
        back = client.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                  vertex_map=forms.vertex_map, placement=forms.placement)
        whole = client.reconstruct(forms)
        report = client.check_integrability(forms.faces, forms.edges, forms.lengths,
                                            forms.angles, vertex_map=forms.vertex_map)
    assert back.vertices.shape == V.shape and np.abs(back.vertices - V).max() < 1e-9
    np.testing.assert_array_equal(back.vertices, whole.vertices)
    assert report.integrable
    # in-process (ffs without --server) the same keywords give the same answer
    from ffs.local import Local

    local = Local().reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles,
                                vertex_map=forms.vertex_map, placement=forms.placement)
    assert np.abs(local.vertices - back.vertices).max() < 1e-9
    assert Local().check_integrability(forms.faces, forms.edges, forms.lengths, forms.angles,
                                       vertex_map=forms.vertex_map).integrable
