"""Time-based admission of the linear answer (``options.refine: false``), on a real uvicorn:
``GET /v1/me``'s ``max_linear_sync_faces_by_operation`` is the synchronous limit the service
holds a linear reconstruction to (its own pricing,
:data:`service.backends.admission.LINEAR_RECONSTRUCTION`), and the Python client chooses
between a synchronous request and a job by it for ``refine=False`` calls.

Both answers' synchronous limits are priced by the time to the first answer, which is the
linear one either way, so today the two numbers are equal (20,021 faces at
FFS_REQUEST_TIMEOUT=0.55, as in ``test_time_admission``): no mesh lies between them. The
limit the service enforces is checked at its two sides (icosphere(4), 5,120 faces: 200;
icosphere(5), 20,480: 413 naming the limit); the client's choice is checked with its cached
limits set apart (the refined one low, the linear one high, and the other way round), by the
requests it sends. A test where the pricings differ is
``test_limits_agree.test_a_linear_answer_is_held_to_its_own_synchronous_limit``.
"""

from __future__ import annotations

import httpx
import numpy as np

import solver
from ffs import Client
from service.backends.admission import LINEAR_RECONSTRUCTION, RECONSTRUCTION
from service.settings import Settings
from tests.helpers.meshes import icosphere
from tests.helpers.servers import uvicorn_fixture
from tests.helpers.service import forms_json, problem, rigid_error

TIMEOUT = 0.55
BUDGET = TIMEOUT - 0.1375  # less the encode margin (service.api.budgets: 0.1375 s of 0.55 s)
MEMORY = Settings(workers=1).max_request_memory  # the server's default, this machine's
server = uvicorn_fixture({"FFS_REQUEST_TIMEOUT": str(TIMEOUT), "FFS_WORKERS": "1"},
                         scope="module")


def _linear(V: np.ndarray, F: np.ndarray, noise: float = 0.0) -> dict:
    """The body of a linear reconstruction of the mesh's forms (angles with ``noise``)."""
    body = forms_json(V, F)
    angles = np.asarray(body["angles"])
    body["angles"] = (angles + noise * np.random.default_rng(3).normal(size=angles.shape)
                      ).tolist()
    return {**body, "options": {"refine": False}}


def test_me_names_the_linear_answers_synchronous_limit(server: str) -> None:
    with httpx.Client(base_url=server, timeout=30) as http:
        sizes = http.get("/v1/me").json()["size_limits"]
    linear = LINEAR_RECONSTRUCTION.sync_faces_within(BUDGET, MEMORY)
    assert sizes["max_linear_sync_faces_by_operation"] == {"reconstruct": linear}
    assert sizes["max_sync_faces_by_operation"]["reconstruct"] == RECONSTRUCTION.sync_faces_within(
        BUDGET, MEMORY)
    assert len(icosphere(4)[1]) < linear < len(icosphere(5)[1])


def test_a_linear_request_is_held_to_the_limit_me_names(server: str) -> None:
    with httpx.Client(base_url=server, timeout=120) as http:
        linear = http.get("/v1/me").json()["size_limits"][
            "max_linear_sync_faces_by_operation"]["reconstruct"]
        V, F = icosphere(4)
        body = _linear(V, F, noise=1e-3)  # not integrable: the linear answer of Eq. 5
        answer = http.post("/v1/reconstruct", json=body)
        assert answer.status_code == 200, answer.text
        assert answer.json()["report"]["refinement"]["refined"] is False
        expected = solver.reconstruct(*(np.asarray(body[k]) for k in (
            "faces", "edges", "lengths", "angles")), refine=False).vertices
        got = np.asarray(answer.json()["vertices"])
        assert rigid_error(got, expected) < 1e-8 < rigid_error(got, V)
        V, F = icosphere(5)
        doc = problem(http.post("/v1/reconstruct", json=_linear(V, F)), 413, "use-a-job")
        assert f"{len(F)} faces exceed the {linear} faces" in doc["detail"], doc


def _sent(client: Client) -> list[str]:
    """The paths of the POST requests ``client`` sends from now on."""
    sent: list[str] = []
    request = client.request

    def recording(method: str, path: str, **kwargs):
        if method == "POST":
            sent.append(path)
        return request(method, path, **kwargs)

    client.request = recording  # type: ignore[method-assign]
    return sent


def test_the_client_chooses_by_the_linear_answers_limit(server: str) -> None:
    """A ``refine=False`` call of icosphere(5) (20,480 faces, over the service's 20,021):
    with the real limits it goes to the job API at once; with a linear limit above the mesh
    (and the refined one below) it is sent synchronously first (and, told 413 use-a-job,
    as a job); with the linear limit below (and the refined one above) straight to the job
    API. The answer is the mesh each time."""
    V, F = icosphere(5)
    forms = solver.fundamental_forms(V, F)
    arrays = (forms.faces, forms.edges, forms.lengths, forms.angles)
    for limits, first in ((None, "/v1/jobs"), (({"reconstruct": 10_001},
                                                {"reconstruct": 10**6}), "/v1/reconstruct"),
                          (({"reconstruct": 10**6}, {"reconstruct": 10_001}), "/v1/jobs")):
        with Client(server, timeout=120) as client:
            if limits is not None:
                client._sync_faces, client._linear_sync_faces = limits
            sent = _sent(client)
            result = client.reconstruct(*arrays, refine=False)
            assert rigid_error(result.vertices, V) < 1e-6
            assert sent[0] == first and "/v1/jobs" in sent, (limits, sent)
            if limits is None:
                assert client._linear_sync_faces == {
                    "reconstruct": LINEAR_RECONSTRUCTION.sync_faces_within(BUDGET, MEMORY)}
