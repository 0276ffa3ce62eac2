"""Issue 46 ("Who may use the service") against a real uvicorn on loopback with API keys:
401 without or with a wrong key, 403 for a role, ownership of jobs and sessions (404 for
another key, over HTTP and the WebSocket; an admin sees and cancels everything), quotas
per key (429 with Retry-After, RateLimit and RateLimit-Policy, the request not executed),
per-key metrics by name, the OpenAPI bearer scheme, and no key material in what the server
wrote."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.helpers import REPO
from tests.helpers.meshes import icosphere
from tests.helpers.servers import server_log, uvicorn_process
from tests.helpers.service import forms_json, metric_value, problem

KEYS = {"alice": "alice-key-0123456789abcdef", "bob": "bob-key-fedcba9876543210",
        "ops": "ops-key-00112233445566778899"}
HANDLES = [0, 40, 80, 120]


def _add_key(path: Path, name: str, *options: str) -> str:
    """``python -m service.access add`` (the documented command); the key it printed."""
    out = subprocess.run(
        [sys.executable, "-m", "service.access", "add", name, "--file", str(path), *options],
        cwd=REPO, capture_output=True, text=True, check=True,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    key = next(line for line in out.stdout.splitlines() if line.startswith("ffs_"))
    stored = path.read_text()
    assert key not in stored and "sha256:" in stored  # only its hash is kept
    assert path.stat().st_mode & 0o077 == 0
    return key


@pytest.fixture(scope="module")
def limited_key(tmp_path_factory) -> tuple[Path, str, str, str]:
    """A keys file with a key of few requests and jobs, one of small meshes and one of a
    single session."""
    path = tmp_path_factory.mktemp("keys") / "keys.json"
    tight = _add_key(path, "tight", "--requests-per-minute", "5", "--concurrent-jobs", "1",
                     "--concurrent-sessions", "1")
    small = _add_key(path, "small", "--max-faces", "100")
    single = _add_key(path, "single", "--concurrent-sessions", "1")
    return path, tight, small, single


@pytest.fixture(scope="module")
def server(limited_key) -> Iterator[str]:
    env = {"FFS_WORKERS": "1", "FFS_API_KEYS": json.dumps(KEYS), "FFS_ADMIN_KEYS": "ops",
           "FFS_API_KEYS_FILE": str(limited_key[0]),
           "FFS_MAX_FACES": "500000"}  # the keys' default face quota below (it follows
    # from the machine's memory when unset)
    with uvicorn_process(env, log_level="info") as (base, _):
        yield base


def _client(base: str, name: str | None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {KEYS[name]}"} if name else {}
    return httpx.Client(base_url=base, timeout=60, headers=headers)


@pytest.fixture(scope="module")
def alice(server) -> Iterator[httpx.Client]:
    with _client(server, "alice") as client:
        yield client


@pytest.fixture(scope="module")
def bob(server) -> Iterator[httpx.Client]:
    with _client(server, "bob") as client:
        yield client


@pytest.fixture(scope="module")
def ops(server) -> Iterator[httpx.Client]:
    with _client(server, "ops") as client:
        yield client


@pytest.fixture(scope="module")
def sphere():
    return icosphere(3)


def _forms_job(V, F) -> dict:
    return {"operation": "reconstruct", "input": forms_json(V, F)}


def _wait(client: httpx.Client, location: str) -> dict:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        doc = client.get(location).json()
        if doc["status"] not in ("queued", "running"):
            return doc
        time.sleep(0.05)
    raise AssertionError(f"{location} did not finish")


def test_no_key_and_a_wrong_key_are_401_with_a_challenge(server, sphere):
    with _client(server, None) as anonymous:
        for method, path in (("GET", "/v1/jobs"), ("POST", "/v1/forms"),
                             ("GET", "/v1/sessions/0123"), ("GET", "/metrics")):
            response = anonymous.request(method, path, json={})
            doc = problem(response, 401, "unauthorized")
            assert response.headers["www-authenticate"] == 'Bearer realm="ffs"'
            assert doc["errors"][0]["field"] == "Authorization"
        wrong = anonymous.get("/v1/jobs", headers={"Authorization": "Bearer not-a-key"})
        problem(wrong, 401, "unauthorized")
        assert 'error="invalid_token"' in wrong.headers["www-authenticate"]
        basic = anonymous.get("/v1/jobs", headers={"Authorization": "Basic YWxpY2U6eA=="})
        problem(basic, 401, "unauthorized")
        # The health checks, the documentation and the problem catalogue stay public.
        for path in ("/healthz", "/readyz", "/openapi.json", "/problems",
                     "/problems/unauthorized", "/docs"):
            assert anonymous.get(path).status_code in (200, 503), path
        # A 401 did not run anything: no forms were computed.
        assert "ffs_tasks_total" not in anonymous.get(
            "/metrics", headers={"Authorization": f"Bearer {KEYS['ops']}"}).text.replace(
            "# HELP ffs_tasks_total", "").replace("# TYPE ffs_tasks_total", "")


def test_metrics_need_the_admin_role_and_count_by_key_name(alice, ops):
    assert alice.get("/v1/jobs").status_code == 200
    forbidden = alice.get("/metrics")
    doc = problem(forbidden, 403, "forbidden")
    assert "admin" in doc["detail"] and "alice" in doc["detail"]
    text = ops.get("/metrics").text
    assert metric_value(text, "ffs_key_requests_total", key="alice") >= 1
    assert metric_value(text, "ffs_auth_refused_total", reason="forbidden") >= 1
    for key in KEYS.values():
        assert key not in text


def test_jobs_belong_to_their_key(alice, bob, ops, sphere):
    V, F = sphere
    submitted = alice.post("/v1/jobs", json=_forms_job(V, F))
    assert submitted.status_code == 202, submitted.text
    location = submitted.headers["location"]
    assert _wait(alice, location)["status"] == "succeeded"
    job_id = location.rsplit("/", 1)[1]
    for method, path in (("GET", location), ("GET", f"{location}/result"),
                         ("GET", f"{location}/mesh"), ("DELETE", location)):
        doc = problem(bob.request(method, path), 404, "not-found")
        assert "alice" not in doc["detail"]
    unknown = problem(bob.get("/v1/jobs/" + "0" * 32), 404, "not-found")
    assert unknown["detail"].replace("0" * 32, job_id) == doc["detail"].replace(
        "/result", "")  # the same answer as for an id that does not exist
    assert job_id not in [j["id"] for j in bob.get("/v1/jobs").json()]
    assert job_id in [j["id"] for j in alice.get("/v1/jobs").json()]
    assert job_id in [j["id"] for j in ops.get("/v1/jobs").json()]  # the admin lists all
    assert ops.get(f"{location}/result").status_code == 200
    assert alice.get(location).status_code == 200  # bob's DELETE did nothing
    # The admin cancels a job of alice's.
    slow = {"operation": "reconstruct",
            "input": {**forms_json(*icosphere(5)), "options": {"exact_shortcut": False}}}
    running = alice.post("/v1/jobs", json=slow).headers["location"]
    cancelled = ops.delete(running)
    assert cancelled.status_code in (200, 204), cancelled.text
    assert alice.get(running).json()["status"] in ("cancelled", "succeeded")


def _session(client: httpx.Client, V, F) -> str:
    response = client.post("/v1/sessions", json={
        "vertices": V.tolist(), "faces": F.tolist(),
        "handles": [{"vertex": h} for h in HANDLES]})
    assert response.status_code == 201, response.text
    return response.headers["location"]


def _ws_url(base: str, location: str) -> str:
    return base.replace("http://", "ws://") + location + "/ws"


def test_sessions_belong_to_their_key_over_http_and_websocket(server, alice, bob, ops, sphere):
    from websockets.exceptions import ConnectionClosed, InvalidStatus
    from websockets.sync.client import connect

    V, F = sphere
    location = _session(alice, V, F)
    drag = {"handle_positions": V[HANDLES].tolist()}
    for method, path, body in (("GET", location, None), ("POST", f"{location}/solve", drag),
                               ("GET", f"{location}/drags/1/refined", None),
                               ("DELETE", location, None)):
        problem(bob.request(method, path, json=body), 404, "not-found")
    assert location.rsplit("/", 1)[1] not in [s["id"] for s in bob.get("/v1/sessions").json()]
    assert location.rsplit("/", 1)[1] in [s["id"] for s in ops.get("/v1/sessions").json()]
    assert alice.post(f"{location}/solve", json=drag).status_code == 200
    assert ops.post(f"{location}/solve", json=drag).status_code == 200  # the admin may drag

    url = _ws_url(server, location)
    payload = np.asarray(V[HANDLES], dtype="<f4").tobytes()
    # Bob, by header and by subprotocol: the session "does not exist".
    for options in ({"additional_headers": {"Authorization": f"Bearer {KEYS['bob']}"}},
                    {"subprotocols": ["ffs", f"bearer.{KEYS['bob']}"]}):
        with connect(url, max_size=None, **options) as ws:
            message = json.loads(ws.recv(timeout=10))
            assert message["status"] == 404 and message["kind"] == "not-found"
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=10)
            assert ws.close_code == 4404
    # No key, or a wrong one: the handshake is refused with 401 (nothing is accepted).
    for options in ({}, {"subprotocols": ["ffs", "bearer.wrong"]}):
        with pytest.raises(InvalidStatus) as refused:
            connect(url, **options)
        assert refused.value.response.status_code == 401
    # Alice, with the key in a subprotocol as a browser sends it, and with the header.
    with connect(url, max_size=None, subprotocols=["ffs", f"bearer.{KEYS['alice']}"]) as ws:
        assert ws.subprotocol == "ffs"  # the key is never echoed
        ws.send(payload)
        assert len(ws.recv(timeout=30)) >= len(V) * 12
    with connect(url, max_size=None,
                 additional_headers={"Authorization": f"Bearer {KEYS['ops']}"}) as ws:
        ws.send(payload)
        assert len(ws.recv(timeout=30)) >= len(V) * 12
    assert ops.delete(location).status_code == 204  # the admin closes it
    problem(alice.get(location), 404, "not-found")


def test_quotas_answer_429_with_both_header_sets_and_run_nothing(server, ops, limited_key,
                                                                 sphere):
    V, F = sphere
    headers = {"Authorization": f"Bearer {limited_key[1]}"}
    with httpx.Client(base_url=server, timeout=60, headers=headers) as tight:
        first = tight.get("/v1/jobs")
        assert first.status_code == 200
        assert first.headers["ratelimit-policy"] == '"requests";q=5;w=60'
        assert first.headers["ratelimit"].startswith('"requests";r=4;t=')
        # Faces per request: a key with max_faces 100 may not send a 1280-face mesh.
        for path, body in (("/v1/forms", {"vertices": V.tolist(), "faces": F.tolist()}),
                           ("/v1/jobs", _forms_job(V, F))):
            big = tight.post(path, json=body, headers={
                "Authorization": f"Bearer {limited_key[2]}"})
            doc = problem(big, 413, "mesh-too-large")
            assert "limit of 100" in doc["detail"]
            # 413, not 429 (retrying does not help), still with the key's rate headers
            assert big.headers["ratelimit-policy"].startswith('"requests";q=')
        # Concurrent jobs: one slow job runs, the second is refused.
        slow = {"operation": "reconstruct",
                "input": {**forms_json(*icosphere(5)), "options": {"exact_shortcut": False}}}
        running = tight.post("/v1/jobs", json=slow)
        assert running.status_code == 202, running.text
        refused = tight.post("/v1/jobs", json=slow)
        doc = problem(refused, 429, "quota-exceeded")
        assert refused.headers["retry-after"] == "5"
        assert refused.headers["ratelimit-policy"] == \
            '"concurrent-jobs";q=1;qu="concurrent-requests"'
        assert refused.headers["ratelimit"].startswith('"concurrent-jobs";r=0;t=')
        assert doc["limit"] == 1 and doc["quota"] == "concurrent-jobs"
        # Requests per minute: the fifth request is the last one of this minute.
        assert [tight.get("/v1/jobs").status_code for _ in range(2)] == [200, 200]
        throttled = tight.post("/v1/jobs", json=_forms_job(V, F))
        doc = problem(throttled, 429, "rate-limited")
        assert 1 <= int(throttled.headers["retry-after"]) <= 60
        assert throttled.headers["ratelimit-policy"] == '"requests";q=5;w=60'
        assert throttled.headers["ratelimit"].startswith('"requests";r=0;t=')
    owned = [j for j in ops.get("/v1/jobs").json() if j["id"] in running.headers["location"]]
    assert len(owned) == 1
    tight_jobs = [j for j in ops.get("/v1/jobs").json()
                  if j["created_at"] >= owned[0]["created_at"] and j["operation"] == "reconstruct"]
    assert len(tight_jobs) == 1  # neither refused submission was executed
    ops.delete(running.headers["location"])
    text = ops.get("/metrics").text
    assert metric_value(text, "ffs_key_throttled_total", key="tight", quota="requests") == 1
    assert metric_value(text, "ffs_key_throttled_total", key="tight",
                        quota="concurrent-jobs") == 1
    assert metric_value(text, "ffs_key_requests_total", key="tight") == 5


def test_openapi_declares_the_bearer_scheme(server):
    document = httpx.get(f"{server}/openapi.json").json()
    assert document["components"]["securitySchemes"]["bearerAuth"] == {
        **document["components"]["securitySchemes"]["bearerAuth"],
        "type": "http", "scheme": "bearer"}
    submit = document["paths"]["/v1/jobs"]["post"]
    assert {"bearerAuth": []} in submit["security"] and "401" in submit["responses"]
    assert document["paths"]["/healthz"]["get"]["security"] == []


def test_me_and_a_refused_upload_is_a_401(server, alice, ops):
    me = alice.get("/v1/me").json()
    sizes = me.pop("size_limits")
    assert me == {
        "keys": True, "name": "alice", "role": "user",
        "limits": {"requests_per_minute": 600, "concurrent_jobs": 16,
                   "concurrent_sessions": 4, "max_faces": 500_000}}
    assert sizes["max_faces"] == 500_000 and sizes["max_vertices"] == 300_000
    # Each operation takes at most FFS_MAX_FACES, those that factorize what fits the memory.
    from service.backends.admission import FACTORIZING, RECONSTRUCTION

    memory = sizes["max_request_memory"]
    by_operation = sizes["max_faces_by_operation"]
    assert by_operation["forms"] == by_operation["mesh"] == 500_000
    assert by_operation["sessions"] == min(FACTORIZING.faces_within(memory), 500_000)
    assert by_operation["reconstruct"] == min(RECONSTRUCTION.faces_within(memory), 500_000)
    assert ops.get("/v1/me").json()["role"] == "admin"
    with _client(server, None) as anonymous:
        problem(anonymous.get("/v1/me"), 401, "unauthorized")
        upload = (REPO / "tests" / "data" / "bar.off").read_bytes()  # 450 KB
        assert len(upload) > 400_000
        for _ in range(3):  # (the service reads up to 1 MiB of it before answering)
            response = anonymous.post("/v1/mesh", files={"file": ("bar.off", upload)})
            problem(response, 401, "unauthorized")


def test_the_session_quota_answers_429_and_opens_nothing(server, ops, limited_key, sphere):
    V, F = sphere
    with httpx.Client(base_url=server, timeout=60,
                      headers={"Authorization": f"Bearer {limited_key[3]}"}) as single:
        first = _session(single, V, F)
        open_before = metric_value(ops.get("/metrics").text, "ffs_sessions")
        refused = single.post("/v1/sessions", json={
            "vertices": V.tolist(), "faces": F.tolist(),
            "handles": [{"vertex": h} for h in HANDLES]})
        doc = problem(refused, 429, "quota-exceeded")
        assert doc["quota"] == "concurrent-sessions" and doc["limit"] == 1
        assert refused.headers["retry-after"] == "5"
        assert refused.headers["ratelimit-policy"] == \
            '"concurrent-sessions";q=1;qu="concurrent-requests"'
        assert refused.headers["ratelimit"].startswith('"concurrent-sessions";r=0;t=')
        # Nothing was opened: the key's list and the service's count are as before.
        assert [x["id"] for x in single.get("/v1/sessions").json()] == [
            first.rsplit("/", 1)[1]]
        text = ops.get("/metrics").text
        assert metric_value(text, "ffs_sessions") == open_before
        assert metric_value(text, "ffs_key_throttled_total", key="single",
                            quota="concurrent-sessions") == 1
        assert single.delete(first).status_code == 204
        assert single.delete(_session(single, V, F)).status_code == 204  # free again


WRONG_KEYS = ("wrong-key-5f0c2a9e7d4113", "wrong-ws-key-0b9d8e7f6a55")
"""Keys nobody has, presented to be refused: they must not be written anywhere either."""


def _refusals(server: str, alice: httpx.Client, bob: httpx.Client, limited_key,
              sphere) -> dict[int, list[str]]:
    """One request on every refusal path (401 without a key, with a wrong one and at the
    WebSocket; 403; 404 over HTTP and the WebSocket; 429 of the request rate and of a
    concurrent quota; 413 of the face quota): each answer's status line, headers and body,
    by status."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    V, F = sphere
    answers: dict[int, list[str]] = {}

    def keep(status: int, headers, body: str) -> None:
        answers.setdefault(status, []).append(f"{status} {dict(headers)} {body}")

    def keep_http(response: httpx.Response) -> httpx.Response:
        keep(response.status_code, response.headers, response.text)
        return response

    def as_key(key: str) -> httpx.Client:
        return httpx.Client(base_url=server, timeout=60,
                            headers={"Authorization": f"Bearer {key}"})

    with _client(server, None) as anonymous:
        keep_http(anonymous.get("/v1/jobs"))
    with as_key(WRONG_KEYS[0]) as wrong:
        keep_http(wrong.post("/v1/forms", json={"vertices": [], "faces": []}))
    keep_http(alice.get("/metrics"))
    location = _session(alice, V, F)
    keep_http(bob.get(location))
    keep_http(bob.post(f"{location}/solve", json={"handle_positions": V[HANDLES].tolist()}))
    url = _ws_url(server, location)
    with connect(url, subprotocols=["ffs", f"bearer.{KEYS['bob']}"]) as ws:
        message = ws.recv(timeout=10)
        keep(json.loads(message)["status"], {}, message)
    for options in ({"subprotocols": ["ffs", f"bearer.{WRONG_KEYS[1]}"]},
                    {"additional_headers": {"Authorization": f"Bearer {WRONG_KEYS[1]}"}}):
        with pytest.raises(InvalidStatus) as refused:
            connect(url, **options)
        response = refused.value.response
        keep(response.status_code, response.headers, response.body.decode())
    with as_key(limited_key[1]) as tight:  # 5 requests a minute
        for _ in range(6):
            if keep_http(tight.get("/v1/jobs")).status_code == 429:
                break
    with as_key(limited_key[3]) as single:  # one session at once
        own = _session(single, V, F)
        keep_http(single.post("/v1/sessions", json={
            "vertices": V.tolist(), "faces": F.tolist(),
            "handles": [{"vertex": h} for h in HANDLES]}))
        single.delete(own)
    with as_key(limited_key[2]) as small:  # meshes of at most 100 faces
        keep_http(small.post("/v1/forms", json={"vertices": V.tolist(), "faces": F.tolist()}))
    alice.delete(location)
    return answers


def test_no_key_material_in_what_the_server_wrote(server, alice, bob, ops, limited_key,
                                                  sphere):
    """After every refusal path, neither the server's output (uvicorn's access and error
    log, the service's log), nor any answer, nor /metrics holds a key, neither the known
    ones nor the wrong ones presented: only key names."""
    answers = _refusals(server, alice, bob, limited_key, sphere)
    assert sorted(answers) == [401, 403, 404, 413, 429], sorted(answers)
    assert len(answers[401]) == 4 and len(answers[404]) == 3 and len(answers[429]) == 2
    alice.get("/v1/jobs", params={"x": "y"})
    time.sleep(0.2)
    log = server_log(server).read_text()
    assert '"GET /v1/jobs?x=y HTTP/1.1" 200' in log  # the access log is on
    assert '"GET /metrics HTTP/1.1" 403' in log and '"POST /v1/forms HTTP/1.1" 401' in log
    metrics = ops.get("/metrics").text
    assert metric_value(metrics, "ffs_key_throttled_total", key="tight") >= 1
    written = {"log": log, "metrics": metrics,
               **{f"answer {status}": "\n".join(texts) for status, texts in answers.items()}}
    for key in (*KEYS.values(), *limited_key[1:], *WRONG_KEYS):
        for where, text in written.items():
            assert key not in text, f"a key in the {where}"
    assert "bearer." not in log
