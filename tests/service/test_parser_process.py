"""Bodies over ``PROCESS_THRESHOLD`` (jobs, sessions) are validated in the parser process:
the same answers and problem documents as in this process, and a parser that died is
replaced (its body answered 503 ``unavailable``, the next one validated again)."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import orjson
import pytest

from service.http import bodies
from solver import fundamental_forms
from tests.helpers.aio import run as run_async
from tests.helpers.meshes import grid
from tests.helpers.servers import running_app
from tests.helpers.service import problem


def big_grid() -> tuple[np.ndarray, np.ndarray]:
    """A bumpy 230 x 230-cell grid (105 800 faces; a 5.0 MiB JSON body, 1.26 times
    ``PROCESS_THRESHOLD``: large enough for the parser, a third of the 399 x 399 grid's
    15.8 MiB, which cost these tests ~20 s more)."""
    V, F = grid(230, 230)
    V[:, 2] = 0.05 * np.sin(7 * V[:, 0]) * np.cos(5 * V[:, 1])
    return V, F


@pytest.fixture(scope="module")
def client():
    with running_app(max_faces=1_000_000) as c:
        yield c


def job_body(vertices: np.ndarray, faces: np.ndarray) -> dict:
    return {"operation": "forms", "input": {"vertices": vertices.tolist(),
                                            "faces": faces.tolist()}}


def test_a_large_job_is_validated_in_the_parser_and_answers_the_right_forms(client):
    V, F = big_grid()
    body = job_body(V, F)
    assert len(orjson.dumps(body)) > bodies.PROCESS_THRESHOLD
    response = client.post("/v1/jobs", json=body)
    assert response.status_code == 202, response.text[:300]
    location = response.headers["location"]
    deadline = time.monotonic() + 120
    doc = client.get(location).json()
    while doc["status"] not in ("succeeded", "failed") and time.monotonic() < deadline:
        time.sleep(0.05)
        doc = client.get(location).json()
    assert doc["status"] == "succeeded", doc
    result = client.get(f"{location}/result").json()
    truth = fundamental_forms(V, F)
    assert np.array_equal(np.asarray(result["edges"]), truth.edges)
    assert np.abs(np.asarray(result["lengths"]) - truth.lengths).max() < 1e-12
    assert np.abs(np.asarray(result["angles"]) - truth.angles).max() < 1e-12


def test_a_large_invalid_session_body_is_the_same_problem_document(client, monkeypatch):
    V, F = big_grid()
    F = F.copy()
    F[12345, 1] = len(V) + 7  # out of range
    body = {"vertices": V.tolist(), "faces": F.tolist(), "handles": [{"vertex": 0}]}
    remote = client.post("/v1/sessions", json=body)
    monkeypatch.setattr(bodies, "PROCESS_THRESHOLD", 10**12)  # now in a thread here
    local = client.post("/v1/sessions", json=body)
    assert remote.status_code == local.status_code == 422
    assert remote.json() == local.json()
    assert str(len(V) + 7) in remote.text


def test_a_dead_parser_is_replaced(client):
    V, F = big_grid()
    body = job_body(V, F)
    assert client.post("/v1/jobs", json=body).status_code == 202  # the parser runs
    parser = client.app.state.services.parser
    dead = parser.pids()
    assert dead
    for pid in dead:
        os.kill(pid, signal.SIGKILL)
    answers = [client.post("/v1/jobs", json=body) for _ in range(2)]
    codes = [a.status_code for a in answers]
    # The death is seen at the first body (503 unavailable) or already before it; either
    # way the next body is validated by a new parser.
    assert codes[-1] == 202, answers[-1].text[:300]
    if codes[0] != 202:
        assert problem(answers[0], 503, "unavailable")["detail"].startswith("the process")
    assert parser.pids() and not set(parser.pids()) & set(dead)


def test_the_parser_starts_and_stops_with_the_service():
    from service.api.problems import ProblemError

    body = job_body(*big_grid())
    with running_app(workers=1, max_faces=1_000_000) as c:
        parser = c.app.state.services.parser
        assert parser.pids() == []  # its process starts with the first large body
        assert c.post("/v1/jobs", json=body).status_code == 202
        pids = parser.pids()
        assert len(pids) == 1
    assert parser.pids() == []  # stopped with the backend, in the lifespan's end
    with pytest.raises(ProcessLookupError):
        os.kill(pids[0], 0)
    with pytest.raises(ProblemError) as info:
        run_async(parser.run(len, b"x"))
    assert info.value.kind == "unavailable" and info.value.status == 503
