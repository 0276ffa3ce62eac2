"""Request admission: each operation's largest mesh follows from its predicted peak memory
(FFS_MAX_REQUEST_MEMORY), and the defaults of FFS_MAX_FACES and FFS_MAX_BODY_BYTES from it."""

from __future__ import annotations

import numpy as np
import pytest

from service.backends.admission import (
    BODY_BYTES_PER_FACE,
    LIGHT_COST,
    SOLVE_COST,
    faces_within,
    request_memory_budget,
)
from service.settings import Settings
from tests.helpers.meshes import icosphere, side_by_side
from tests.helpers.servers import running_app
from tests.helpers.service import forms_json, mesh_json, problem

GIB = 2**30


@pytest.mark.parametrize(("faces", "measured_gb", "cost"), [
    # The measurements (peak RSS, nefertiti subdivided, noisy forms, default answer)
    (388_000, 3.8, SOLVE_COST), (1_550_000, 18.1, SOLVE_COST),
    # bench.scale, the exact (tree) path after issue 45's first commits
    (399_752, 0.82, LIGHT_COST), (1_599_008, 2.78, LIGHT_COST)])
def test_cost_model_meets_the_measured_peaks(faces, measured_gb, cost):
    predicted = cost.memory_bytes(faces) / 1e9
    assert measured_gb * 0.95 <= predicted <= measured_gb * 1.6, predicted


@pytest.mark.parametrize("memory_gb", [0.25, 1, 8, 20])
def test_faces_within_inverts_the_prediction(memory_gb):
    memory = int(memory_gb * GIB)
    for cost, solves in ((SOLVE_COST, True), (LIGHT_COST, False)):
        m = faces_within(memory, solves)
        assert m > 0
        assert cost.memory_bytes(m) <= memory < cost.memory_bytes(int(m * 1.001) + 2)
    assert faces_within(int(0.1 * GIB), solves=True) == 0   # less than the process itself


def test_defaults_follow_from_the_request_memory():
    settings = Settings(workers=2, max_session_memory=4 * GIB, max_request_memory=9 * GIB)
    assert settings.max_faces == faces_within(9 * GIB, solves=False)
    assert settings.max_faces > 1_600_000           # a 1.6M-face scan can be read...
    assert settings.max_body_bytes >= 1_600_000 * BODY_BYTES_PER_FACE  # ...and sent as JSON
    assert settings.max_vertices == 3 * settings.max_faces // 5
    # Given values win; the body limit never drops below 64 MiB.
    small = Settings(max_faces=1000)
    assert (small.max_faces, small.max_vertices, small.max_body_bytes) == (1000, 600, 64 * 2**20)
    # The default request memory is the workers' share of what the sessions leave.
    assert request_memory_budget(24 * GIB, 4 * GIB, 2) == int(0.8 * 20 * GIB / 2)
    assert Settings(workers=1).max_request_memory > Settings(workers=4).max_request_memory
    # Sessions never take more than half, and a request always has at least 1 GiB.
    assert request_memory_budget(8 * GIB, 6 * GIB, 1) == int(0.8 * 4 * GIB)
    assert request_memory_budget(2 * GIB, 4 * GIB, 8) == GIB
    # With Dask the requests run on the cluster's workers (4 GiB each in docker-compose.yml).
    dask = Settings(executor="dask", dask_scheduler_address="tcp://scheduler:8786")
    assert dask.max_request_memory == 4 * GIB


def test_a_request_that_cannot_fit_is_413_naming_the_memory():
    memory = 250 * 2**20
    solve_fit, light_fit = faces_within(memory, True), faces_within(memory, False)
    V, F = side_by_side(icosphere(4), icosphere(4))        # 10 240 faces
    assert solve_fit < len(F) < light_fit
    small_V, small_F = icosphere(4)                          # 5 120 faces
    assert len(small_F) < solve_fit
    with running_app(workers=1, max_request_memory=memory) as app:
        # Reading the forms needs no factorization: it fits.
        forms = app.post("/v1/forms", json=mesh_json(V, F))
        assert forms.status_code == 200, forms.text
        assert len(forms.json()["faces"]) == len(F)
        for body in (forms_json(V, F),):
            doc = problem(app.post("/v1/reconstruct", json=body), 413, "mesh-too-large")
            assert "FFS_MAX_REQUEST_MEMORY" in doc["detail"]
            assert f"{len(F)} faces" in doc["detail"] and str(solve_fit) in doc["detail"]
            doc = problem(app.post("/v1/jobs", json={"operation": "reconstruct",
                                                     "input": body}), 413, "mesh-too-large")
            assert "FFS_MAX_REQUEST_MEMORY" in doc["detail"]
        doc = problem(app.post("/v1/deform", json={**mesh_json(V, F), "handles": [
            {"vertex": 0, "position": [0.0, 0.0, 0.0]}]}), 413, "mesh-too-large")
        # A mesh that fits is solved as before.
        done = app.post("/v1/reconstruct", json=forms_json(small_V, small_F))
        assert done.status_code == 200, done.text
        assert np.asarray(done.json()["vertices"]).shape == small_V.shape
        assert app.get("/readyz").status_code == 200


def test_the_client_sees_the_limits_and_the_413():
    """A real uvicorn: ``ffs.Client.size_limits`` (``GET /v1/me``) shows each operation's
    largest mesh, and a mesh over it raises the 413 naming the memory."""
    from ffs import Client
    from ffs.errors import PayloadTooLargeError
    from tests.helpers.servers import uvicorn_process

    memory = 250 * 2**20
    V, F = side_by_side(icosphere(4), icosphere(4))        # 10 240 faces
    with uvicorn_process({"FFS_WORKERS": "1", "FFS_MAX_REQUEST_MEMORY": str(memory)}) as (
            base, _), Client(base) as client:
        sizes = client.size_limits()
        assert sizes["max_request_memory"] == memory
        assert sizes["max_faces"] == faces_within(memory, solves=False)
        by_operation = sizes["max_faces_by_operation"]
        assert by_operation["forms"] == by_operation["integrability"] == sizes["max_faces"]
        for name in ("reconstruct", "deform", "parameterize", "interpolate", "sessions"):
            assert by_operation[name] == faces_within(memory, solves=True) < len(F)
        forms = client.fundamental_forms(V, F)
        assert len(forms.faces) == len(F)
        with pytest.raises(PayloadTooLargeError, match="FFS_MAX_REQUEST_MEMORY") as caught:
            client.reconstruct(forms)
        assert caught.value.kind == "mesh-too-large"
