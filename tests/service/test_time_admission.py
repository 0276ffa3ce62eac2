"""Time-based admission (issue 45), on a real uvicorn: a synchronous request whose first
answer is predicted to miss FFS_REQUEST_TIMEOUT is answered 413 ``use-a-job`` (saying how
to submit it as a job) before anything is solved; the same input as a job succeeds; the
Python client takes the job path by itself and returns the library's answer.

FFS_REQUEST_TIMEOUT=0.55 leaves the solver 0.4125 s: the prediction
(:func:`service.backends.admission.sync_faces_within`) admits 20,021 faces for operations
that factorize (by a factorization: this machine's request memory holds their factors) and
34,375 for the others, so icosphere(5) (20,480 faces) is refused for ``reconstruct`` and
taken for ``forms``, and icosphere(4) (5,120) is taken for both.

The limit is lowered for the meshes, not the meshes raised to the limit: at
FFS_REQUEST_TIMEOUT=2 (58,711 and 125,000 faces) the large mesh had to be icosphere(6)
(81,920 faces), four times the solving and encoding in every job here. The synchronous
requests that must succeed keep their margin: forms of 20,480 faces answer in ~0.2 s of
0.41 s on a loaded machine (81,920 faces: ~0.8 s of 1.5 s).
"""

from __future__ import annotations

import time

import httpx
import numpy as np

import solver
from ffs import Client
from service.backends.admission import FACTORIZING, LIGHT, RECONSTRUCTION
from service.settings import Settings
from tests.helpers.meshes import icosphere
from tests.helpers.servers import uvicorn_fixture
from tests.helpers.service import forms_json, mesh_json, problem, rigid_error

TIMEOUT = 0.55
BUDGET = TIMEOUT - 0.1375  # less the encode margin (service.api.budgets: 0.1375 s of 0.55 s)
BIG = 5
"""Subdivisions of the sphere too large for a synchronous reconstruction (20,480 faces)."""
MEMORY = Settings(workers=1).max_request_memory  # the server's default, this machine's
server = uvicorn_fixture({"FFS_REQUEST_TIMEOUT": str(TIMEOUT), "FFS_WORKERS": "1"},
                         scope="module")


def test_the_meshes_sit_on_both_sides_of_the_prediction() -> None:
    big, small = len(icosphere(BIG)[1]), len(icosphere(4)[1])
    for pricing in (RECONSTRUCTION, FACTORIZING):
        assert small < pricing.sync_faces_within(BUDGET, MEMORY) < big
    assert big < LIGHT.sync_faces_within(BUDGET, MEMORY)


def _wait(http: httpx.Client, location: str) -> dict:
    for _ in range(1200):
        status = http.get(location).json()
        if status["status"] in ("succeeded", "failed", "cancelled"):
            return status
        time.sleep(0.05)
    raise AssertionError(f"job not done: {status}")


def test_a_request_too_slow_for_sync_is_sent_to_the_job_api(server: str) -> None:
    V, F = icosphere(BIG)
    body = forms_json(V, F)
    with httpx.Client(base_url=server, timeout=120) as http:
        doc = problem(http.post("/v1/reconstruct", json=body), 413, "use-a-job")  # not 504
        assert "POST /v1/jobs" in doc["detail"] and "FFS_REQUEST_TIMEOUT" in doc["detail"]
        assert f"{len(F)} faces" in doc["detail"] and doc["job"] == "/v1/jobs"
        # what it says to do works
        answer = http.post("/v1/jobs", json={"operation": "reconstruct", "input": body})
        assert answer.status_code == 202, answer.text
        assert _wait(http, answer.headers["location"])["status"] == "succeeded"
        result = http.get(answer.headers["location"] + "/result").json()
        assert rigid_error(np.asarray(result["vertices"]), V) < 1e-6
        # the light operation on the same mesh, and the solve on a smaller one, run
        assert http.post("/v1/forms", json=mesh_json(V, F)).status_code == 200
        small = icosphere(4)
        assert http.post("/v1/reconstruct", json=forms_json(*small)).status_code == 200


def test_a_too_slow_upload_is_refused_too(server: str) -> None:
    from solver.mesh.io import save_mesh

    V, F = icosphere(BIG)
    with httpx.Client(base_url=server, timeout=120) as http:
        response = http.post("/v1/parameterize", files={"file": ("m.ply",
                                                                 save_mesh(V, F, "ply"))})
        problem(response, 413, "use-a-job")


def test_me_names_the_synchronous_limits(server: str) -> None:
    with httpx.Client(base_url=server, timeout=30) as http:
        limits = http.get("/v1/me").json()["size_limits"]["max_sync_faces_by_operation"]
    assert limits["reconstruct"] == RECONSTRUCTION.sync_faces_within(BUDGET, MEMORY)
    assert limits["deform"] == FACTORIZING.sync_faces_within(BUDGET, MEMORY)
    assert limits["forms"] == LIGHT.sync_faces_within(BUDGET, MEMORY)


def test_the_client_takes_the_job_path_by_itself(server: str) -> None:
    """The client reads the synchronous limits once and sends a larger call to the job API;
    told 413 use-a-job (a service that does not name its limits: the cache emptied here),
    it submits the call as a job too. Either way the answer is the library's."""
    V, F = icosphere(BIG)
    forms = solver.fundamental_forms(V, F)
    arrays = (forms.faces, forms.edges, forms.lengths, forms.angles)
    expected = solver.reconstruct(*arrays).vertices
    for binary, limits_known in ((True, True), (False, True), (True, False)):
        with Client(server, timeout=120, binary=binary) as client:
            if not limits_known:
                client._sync_faces = {}
            before = len(client.request("GET", "/v1/jobs").json())
            result = client.reconstruct(*arrays)
            np.testing.assert_allclose(result.vertices, expected, atol=1e-9)
            assert len(client.request("GET", "/v1/jobs").json()) == before  # discarded
            assert (client._sync_faces or {}).get("reconstruct") == (
                RECONSTRUCTION.sync_faces_within(BUDGET, MEMORY) if limits_known else None)
