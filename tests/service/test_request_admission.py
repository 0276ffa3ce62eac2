"""Request admission: each operation's largest mesh follows from its predicted peak memory
(FFS_MAX_REQUEST_MEMORY), and the defaults of FFS_MAX_FACES and FFS_MAX_BODY_BYTES from it."""

from __future__ import annotations

import numpy as np
import pytest

from service.backends.admission import (
    BODY_BYTES_PER_FACE,
    FACTORIZING,
    ITERATIVE_COST,
    LIGHT,
    LIGHT_COST,
    LINEAR_ITERATIVE_COST,
    LINEAR_RECONSTRUCTION,
    RECONSTRUCTION,
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
    (399_752, 0.82, LIGHT_COST), (1_599_008, 2.78, LIGHT_COST),
    # bench.scale, the iterative paths (bench/README.md "Memory in place" and "The hierarchy
    # set up level by level", 2026-12-07): refined by CG, and the linear answer by CG
    (99_938, 0.440, ITERATIVE_COST), (399_752, 1.451, ITERATIVE_COST),
    (1_599_008, 5.487, ITERATIVE_COST),
    (99_938, 0.345, LINEAR_ITERATIVE_COST), (399_752, 1.006, LINEAR_ITERATIVE_COST),
    (1_599_008, 3.753, LINEAR_ITERATIVE_COST)])
def test_cost_model_meets_the_measured_peaks(faces, measured_gb, cost):
    predicted = cost.memory_bytes(faces) / 1e9
    assert measured_gb * 0.95 <= predicted <= measured_gb * 1.6, predicted


@pytest.mark.parametrize("memory_gb", [0.25, 1, 8, 20])
def test_faces_within_inverts_the_prediction(memory_gb):
    memory = int(memory_gb * GIB)
    for how in (FACTORIZING, LIGHT):
        m = faces_within(memory, how)
        assert m > 0
        assert how.direct.memory_bytes(m) <= memory < how.direct.memory_bytes(int(m * 1.001) + 2)
    assert faces_within(int(0.1 * GIB), FACTORIZING) == 0   # less than the process itself


@pytest.mark.parametrize("memory_gb", [0.3, 0.4, 1, 4, 7.8, 12, 20])
@pytest.mark.parametrize("how", [RECONSTRUCTION, LINEAR_RECONSTRUCTION])
def test_a_reconstruction_is_priced_by_the_path_its_solver_takes(memory_gb, how):
    """Admitted exactly where the path the solver's own rules choose within the memory is
    predicted to fit it: the factorization where its model fits, the iterative path beyond
    (never a path that does not fit; refused where neither does)."""
    memory = memory_gb * GIB
    fit = faces_within(memory, how)
    assert fit >= how.direct_faces(memory)
    for n in np.unique(np.geomspace(1000, 3e6, 400).astype(int)):
        path = how.choice.choose(int(n), "auto", memory)
        cost = how.iterative if path == "iterative" else how.direct
        assert (cost.memory_bytes(int(n)) <= memory) == (n <= fit), (n, path)
        assert how.memory_bytes(int(n), memory) == cost.memory_bytes(int(n))


def test_the_iterative_path_admits_more_at_this_machine_s_budget():
    """At 7.8 GiB per request (this 24 GiB machine, two workers) the factorization fits
    767K faces of a refined reconstruction; beyond, the solver refines by CG (3.6 KB per
    face, where a 1.6M-face default answer measured 5.5 GB): about 2.28M faces, and the
    linear answer by CG (150 MB + 2.6 KB per face, 3.75 GiB measured at 1.6M) 3.16M. Operations
    without an iterative path keep
    the factorization's limit; the synchronous limit follows the path's time (CG is
    single-threaded and slower: the first answer beyond Eq. 5's factorization misses 2
    minutes)."""
    memory = 7.8 * GIB
    assert FACTORIZING.faces_within(memory) == RECONSTRUCTION.direct_faces(memory)
    assert 760_000 < RECONSTRUCTION.direct_faces(memory) < 775_000
    assert 2_250_000 < RECONSTRUCTION.faces_within(memory) < 2_300_000
    assert 3_140_000 < LINEAR_RECONSTRUCTION.faces_within(memory) < 3_190_000
    # The first answer: by a factorization up to Eq. 5's crossing (8.3 KB per face).
    crossing = LINEAR_RECONSTRUCTION.direct_faces(memory)
    assert RECONSTRUCTION.sync_faces_within(115, memory) == crossing
    assert RECONSTRUCTION.sync_faces_within(1e4, memory) > 2_000_000   # CG, given the time
    assert RECONSTRUCTION.sync_faces_within(10, memory) == SOLVE_COST.first_answer.within(10)


def test_defaults_follow_from_the_request_memory():
    settings = Settings(workers=2, max_session_memory=4 * GIB, max_request_memory=9 * GIB)
    assert settings.max_faces == faces_within(9 * GIB, LIGHT)
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
    memory = 315 * 2**20
    solve_fit, light_fit = faces_within(memory, RECONSTRUCTION), faces_within(memory, LIGHT)
    V, F = side_by_side(icosphere(5), icosphere(5))        # 40 960 faces
    assert solve_fit < len(F) < light_fit
    small_V, small_F = icosphere(5)                          # 20 480 faces
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

    memory = 315 * 2**20
    V, F = side_by_side(icosphere(5), icosphere(5))        # 40 960 faces
    with uvicorn_process({"FFS_WORKERS": "1", "FFS_MAX_REQUEST_MEMORY": str(memory)}) as (
            base, _), Client(base) as client:
        sizes = client.size_limits()
        assert sizes["max_request_memory"] == memory
        assert sizes["max_faces"] == faces_within(memory, LIGHT)
        by_operation = sizes["max_faces_by_operation"]
        assert by_operation["forms"] == by_operation["integrability"] == sizes["max_faces"]
        for name in ("deform", "parameterize", "interpolate", "sessions"):
            assert by_operation[name] == faces_within(memory, FACTORIZING) < len(F)
        # A reconstruction is admitted where either path fits (here the refinement by CG's).
        assert by_operation["reconstruct"] == faces_within(memory, RECONSTRUCTION) < len(F)
        forms = client.fundamental_forms(V, F)
        assert len(forms.faces) == len(F)
        with pytest.raises(PayloadTooLargeError, match="FFS_MAX_REQUEST_MEMORY") as caught:
            client.reconstruct(forms)
        assert caught.value.kind == "mesh-too-large"


def test_beyond_the_factorization_a_reconstruction_runs_iteratively():
    """A real uvicorn whose requests may use 324 MiB: the factorization of a linear answer
    fits ~41K faces there, its iterative path ~73K (the models of 8.3 KB per face against
    150 MB + 2.6 KB), the refined answer by CG ~39K (200 MB + 3.6 KB). A 54K-face linear
    reconstruction, which the old pricing (every
    solving request by the refined factorization's peak) refused, is admitted, its worker
    handed the same budget solves it by CG (the report says so) to the factorization's
    answer; the refined answer of the same forms and an 80K-face linear answer fit neither
    path and are refused in words with the numbers."""
    import httpx

    import solver
    from tests.helpers.meshes import bumpy_grid
    from tests.helpers.servers import uvicorn_process

    memory = 324 * 2**20
    direct, fit = LINEAR_RECONSTRUCTION.direct_faces(memory), LINEAR_RECONSTRUCTION.faces_within(
        memory)
    refined = RECONSTRUCTION.faces_within(memory)
    V, F = bumpy_grid(180, 150)                                  # 54 000 faces
    assert refined < direct < len(F) <= fit
    assert FACTORIZING.faces_within(memory) < len(F)             # the old limit
    forms = solver.fundamental_forms(V, F)
    angles = forms.angles + np.random.default_rng(1).normal(scale=1e-3, size=len(forms.angles))
    body = {"faces": forms.faces.tolist(), "edges": forms.edges.tolist(),
            "lengths": forms.lengths.tolist(), "angles": angles.tolist()}
    linear = {**body, "options": {"refine": False}}
    truth = solver.reconstruct(forms.faces, forms.edges, forms.lengths, angles, refine=False,
                               linear_solver="direct")
    big_V, big_F = bumpy_grid(200, 200)                          # 80 000 faces
    assert len(big_F) > fit
    # FFS_MAX_FACES above both meshes: its default (what the light operations fit in the
    # memory, ~50K faces here) would refuse them before the memory's pricing does.
    env = {"FFS_WORKERS": "1", "FFS_MAX_REQUEST_MEMORY": str(memory), "FFS_MAX_FACES": "100000"}
    with uvicorn_process(env) as (base, _), httpx.Client(base_url=base, timeout=300) as http:
        sizes = http.get("/v1/me").json()["size_limits"]
        assert sizes["max_faces_by_operation"]["reconstruct"] == refined
        assert sizes["max_direct_faces_by_operation"] == {
            "reconstruct": RECONSTRUCTION.direct_faces(memory)}
        assert sizes["max_linear_faces_by_operation"] == {"reconstruct": fit}
        answer = http.post("/v1/reconstruct", json=linear)
        assert answer.status_code == 200, answer.text
        report = answer.json()["report"]
        assert report["solve_path"] == "iterative"
        assert report["linear_solver"]["method"] == "iterative"
        assert report["linear_solver"]["converged"] and report["linear_solver"]["iterations"] > 0
        vertices = np.asarray(answer.json()["vertices"])
        scale = np.abs(truth.vertices).max()
        assert np.abs(vertices - truth.vertices).max() < 1e-6 * scale
        doc = problem(http.post("/v1/reconstruct", json=body), 413, "mesh-too-large")
        assert f"{len(F)} faces exceed the {refined} faces" in doc["detail"]
        assert "FFS_MAX_REQUEST_MEMORY" in doc["detail"]
        assert f"its linear answer (options.refine: false) fits up to {fit} faces" in \
            doc["detail"]
        big = solver.fundamental_forms(big_V, big_F)
        doc = problem(http.post("/v1/reconstruct", json={
            "faces": big.faces.tolist(), "edges": big.edges.tolist(),
            "lengths": big.lengths.tolist(), "angles": big.angles.tolist(),
            "options": {"refine": False}}), 413, "mesh-too-large")
        assert (f"{len(big_F)} faces exceed the {fit} faces this operation can take in the "
                "0.3 GiB one request may use (FFS_MAX_REQUEST_MEMORY) by either path: a "
                f"factorization fits {direct} faces, the iterative solver "
                f"(options.linear_solver) {fit}") in doc["detail"]
