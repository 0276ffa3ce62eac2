"""Interactive deformation sessions on the local executor: create, solve (JSON, float32,
GLB, binary drags), equality with Deformer.solve, errors, the session cap and memory limit,
expiry, delete, worker death, solve timeout, concurrent sessions, and WebSocket round trips
against a real uvicorn server."""

from __future__ import annotations

import json
import os
import signal
import struct
import threading
import time

import httpx
import numpy as np
import pytest

from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app, uvicorn_server
from tests.helpers.service import problem
from tests.helpers.sessions import reference_solves, rotation_z

HANDLES = [0, 40, 80, 120]
GROUP = list(range(500, 506))


def _targets(V, count, seed=0):
    """Handle targets near rest, exactly representable in float32 (so binary drags and
    JSON drags solve the same problem)."""
    rng = np.random.default_rng(seed)
    steps = rng.integers(-64, 64, size=(count, len(HANDLES), 3)) / 512.0
    rest = np.round(V[HANDLES] * 1024) / 1024
    return rest[None] + steps


def _threads(client):
    """BLAS threads of the app's session processes (the reference must use as many)."""
    return client.app.state.services.backend.sessions.policy.threads


def _create(client, V, F, **extra):
    body = {"vertices": V.tolist(), "faces": F.tolist(),
            "handles": [{"vertex": h} for h in HANDLES], **extra}
    response = client.post("/v1/sessions", json=body)
    assert response.status_code == 201, response.text
    return response


@pytest.fixture(scope="module")
def sphere():
    return icosphere(3)


def test_create_and_solve_many_times_equals_deformer(client, sphere):
    V, F = sphere
    response = _create(client, V, F, rotations=[{"faces": GROUP}])
    doc = response.json()
    location = response.headers["location"]
    assert location == f"/v1/sessions/{doc['id']}" == doc["links"]["self"]
    assert doc["n_vertices"] == len(V) and doc["n_faces"] == len(F)
    assert doc["handles"] == HANDLES and doc["n_rotation_groups"] == 1
    assert doc["executor"] == "local" and doc["backend"] in ("pardiso", "cholespy", "superlu")
    assert doc["setup_seconds"] > 0 and 0 < doc["expires_in"] <= 600
    assert doc["memory_bytes"] > 1_000_000

    targets = _targets(V, 12)
    rotations = np.stack([rotation_z(0.05 * i)[None] for i in range(12)])
    want = reference_solves(V, F, HANDLES, targets, groups=[GROUP], rotations=rotations,
                            threads=_threads(client))
    for i, target in enumerate(targets):
        r = client.post(f"{location}/solve", json={
            "handle_positions": target.tolist(), "handle_rotations": rotations[i].tolist()})
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == "application/json"
        assert "solve;dur=" in r.headers["server-timing"]
        assert np.array_equal(np.asarray(r.json()["vertices"]), want[i]), i  # to the last bit
    # Raw float32 vertices; binary drag in, identity rotation by default.
    plain = reference_solves(V, F, HANDLES, targets[:2], groups=[GROUP],
                             threads=_threads(client))
    raw = client.post(f"{location}/solve", json={"handle_positions": targets[0].tolist()},
                      headers={"accept": "application/octet-stream"})
    assert raw.headers["content-type"] == "application/octet-stream"
    assert np.array_equal(np.frombuffer(raw.content, "<f4").reshape(-1, 3),
                          plain[0].astype(np.float32))
    binary = client.post(f"{location}/solve", content=targets[1].astype("<f4").tobytes(),
                         headers={"content-type": "application/octet-stream"})
    assert np.array_equal(np.asarray(binary.json()["vertices"]), plain[1])
    glb = client.post(f"{location}/solve", json={"handle_positions": targets[1].tolist()},
                      headers={"accept": "model/gltf-binary"})
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    state = client.get(location).json()
    assert state["solves"] == 15 and state["id"] == doc["id"]
    assert client.delete(location).status_code == 204
    problem(client.get(location), 404, "not-found")
    problem(client.post(f"{location}/solve", json={"handle_positions": targets[0].tolist()}),
            404, "not-found")
    problem(client.delete(location), 404, "not-found")


def test_session_errors(client, sphere):
    V, F = sphere
    unknown = "/v1/sessions/0123456789abcdef0123456789abcdef"
    problem(client.get(unknown), 404, "not-found")
    problem(client.post(f"{unknown}/solve", json={"handle_positions": [[0, 0, 0]]}), 404,
            "not-found")
    body = {"vertices": V.tolist(), "faces": F.tolist(), "handles": [{"vertex": 9999}]}
    doc = problem(client.post("/v1/sessions", json=body), 422, "index-out-of-range")
    assert doc["errors"][0]["field"] == "handles"
    problem(client.post("/v1/sessions", json={"vertices": V.tolist(), "faces": F.tolist(),
                                              "handles": []}), 422, "validation-error")
    problem(client.post("/v1/sessions", content=b"x", headers={"content-type": "text/plain"}),
            415, "unsupported-media-type")

    location = _create(client, V, F).headers["location"]
    try:
        doc = problem(client.post(f"{location}/solve", json={"handle_positions": [[0, 0, 0]]}),
                      422, "validation-error")
        assert "expected 4 positions" in doc["detail"]
        problem(client.post(f"{location}/solve", json={"handle_positions": [[0, 0, "x"]] * 4}),
                422, "validation-error")
        problem(client.post(f"{location}/solve", content=b"\0" * 10,
                            headers={"content-type": "application/octet-stream"}),
                422, "validation-error")
        problem(client.post(f"{location}/solve", content=b"{",
                            headers={"content-type": "application/json"}), 400, "malformed-json")
        # NaN, as Python's json writes it, is named like every non-finite value (422), not
        # called malformed JSON (400 "unexpected character"; newcomer sweep)
        drag = json.dumps({"handle_positions": [[0, 0, 0]] * 3 + [[0, 0, float("nan")]]})
        doc = problem(client.post(f"{location}/solve", content=drag.encode(),
                                  headers={"content-type": "application/json"}),
                      422, "validation-error")
        assert doc["errors"][0]["field"] == "handle_positions", doc
        problem(client.post(f"{location}/solve", json={"handle_positions": [[0, 0, 0]] * 4},
                            headers={"accept": "text/csv"}), 406, "not-acceptable")
        # The session survives bad drags.
        assert client.post(f"{location}/solve",
                           json={"handle_positions": V[HANDLES].tolist()}).status_code == 200
    finally:
        client.delete(location)


def test_cap_memory_limit_expiry_worker_death_and_timeout(sphere):
    V, F = sphere
    small_V, small_F = icosphere(2)
    with running_app(workers=1, max_sessions=2, session_ttl=30.0) as c:
        sessions = c.app.state.services.backend.sessions
        first = _create(c, V, F).headers["location"]
        second = _create(c, small_V, small_F).headers["location"]
        # Cap on live sessions: 429 with Retry-After.
        full = c.post("/v1/sessions", json={"vertices": small_V.tolist(),
                                            "faces": small_F.tolist(),
                                            "handles": [{"vertex": 0}]})
        doc = problem(full, 429, "too-many-sessions")
        assert int(full.headers["retry-after"]) >= 1 and doc["limit"] == 2
        assert "FFS_MAX_SESSIONS" in doc["detail"]
        assert c.delete(second).status_code == 204

        # Memory limit: 503 with a clear body.
        sessions.policy.max_memory = sessions.memory() + 1024
        doc = problem(c.post("/v1/sessions", json={"vertices": small_V.tolist(),
                                                   "faces": small_F.tolist(),
                                                   "handles": [{"vertex": 0}]}),
                      503, "session-memory")
        assert "FFS_MAX_SESSION_MEMORY" in doc["detail"] and doc["memory_limit"] > 0
        sessions.policy.max_memory = 8 * 1024**3

        # Worker death: 410 with the reason, never a hang; other sessions keep working.
        victim = _create(c, small_V, small_F).headers["location"]
        victim_id = victim.rsplit("/", 1)[1]
        os.kill(sessions.pids()[victim_id], signal.SIGKILL)
        target = {"handle_positions": small_V[HANDLES].tolist()}
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            r = c.post(f"{victim}/solve", json=target)
            if r.status_code == 410:
                break
        doc = problem(r, 410, "session-gone")
        assert "SIGKILL" in doc["detail"] and "died" in doc["reason"]
        problem(c.get(victim), 410, "session-gone")
        assert c.post(f"{first}/solve", json={"handle_positions": V[HANDLES].tolist()}
                      ).status_code == 200

        # A solve beyond FFS_SESSION_SOLVE_TIMEOUT: 504, then the session is gone (410).
        # (0 s: no reply can be there yet; 1e-4 s was raced by a fast reply on a quiet box.)
        sessions.policy.solve_timeout = 0.0
        problem(c.post(f"{first}/solve", json={"handle_positions": V[HANDLES].tolist()}),
                504, "timeout")
        sessions.policy.solve_timeout = 30.0
        doc = problem(c.get(first), 410, "session-gone")
        assert "FFS_SESSION_SOLVE_TIMEOUT" in doc["detail"]
        assert sessions.count() == 0

        # Idle expiry (the sweeper's work, run here at once): 410 for one more TTL, then 404.
        idle = _create(c, small_V, small_F).headers["location"]
        sessions.policy.ttl = 0.5
        time.sleep(0.7)
        assert c.portal.call(sessions.expire) == 1
        doc = problem(c.get(idle), 410, "session-gone")
        assert "FFS_SESSION_TTL" in doc["detail"]
        time.sleep(0.7)
        c.portal.call(sessions.expire)
        problem(c.get(idle), 404, "not-found")
        metrics = c.get("/metrics").text
        assert "ffs_sessions 0.0" in metrics and "ffs_sessions_created_total 4.0" in metrics
        assert 'ffs_session_solve_duration_seconds_count{transport="http"}' in metrics


def test_concurrent_sessions_do_not_mix(client, sphere):
    V, F = sphere
    meshes = [sphere, icosphere(2), (V * 2.0, F)]
    locations = [_create(client, mV, mF).headers["location"] for mV, mF in meshes]
    targets = [_targets(mV, 6, seed=i) for i, (mV, _) in enumerate(meshes)]
    wants = [reference_solves(mV, mF, HANDLES, t, threads=_threads(client))
             for (mV, mF), t in zip(meshes, targets, strict=True)]
    errors: list[str] = []

    def drag(k: int) -> None:
        for i, target in enumerate(targets[k]):
            r = client.post(f"{locations[k]}/solve", json={"handle_positions": target.tolist()})
            if r.status_code != 200 or not np.array_equal(np.asarray(r.json()["vertices"]),
                                                          wants[k][i]):
                errors.append(f"session {k} drag {i}: {r.status_code}")

    threads = [threading.Thread(target=drag, args=(k,)) for k in range(3) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    for location in locations:
        assert client.delete(location).status_code == 204
    assert not errors, errors


def _ws_url(base: str, location: str) -> str:
    return base.replace("http://", "ws://") + location + "/ws"


def _reply(message: bytes) -> tuple[int, np.ndarray]:
    seq, n = struct.unpack("<II", message[:8])
    vertices = np.frombuffer(message[8:], "<f4").reshape(-1, 3)
    assert len(vertices) == n
    return seq, vertices


def test_websocket_round_trips_on_a_real_server(sphere):
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    V, F = sphere
    targets = _targets(V, 40, seed=7)
    want = reference_solves(V, F, HANDLES, targets, threads=1).astype(np.float32)
    env = {"FFS_WORKERS": "1", "FFS_SESSION_THREADS": "1"}
    with uvicorn_server(env) as base, httpx.Client(base_url=base, timeout=60) as http:
        location = _create(http, V, F).headers["location"]
        http_result = http.post(f"{location}/solve",
                                json={"handle_positions": targets[0].tolist()},
                                headers={"accept": "application/octet-stream"})
        assert np.array_equal(np.frombuffer(http_result.content, "<f4").reshape(-1, 3), want[0])
        with connect(_ws_url(base, location), max_size=None) as ws:
            # Binary drags: seq counts the messages on this connection.
            for i in range(3):
                ws.send(targets[i].astype("<f4").tobytes())
                seq, vertices = _reply(ws.recv(timeout=30))
                assert seq == i + 1 and np.array_equal(vertices, want[i])
            # JSON drags carry their own seq.
            ws.send(json.dumps({"handle_positions": targets[3].tolist(), "seq": 1000}))
            seq, vertices = _reply(ws.recv(timeout=30))
            assert seq == 1000 and np.array_equal(vertices, want[3])
            # A bad message gets a problem document (text), the connection stays open.
            ws.send(b"\0\0\0")
            error = json.loads(ws.recv(timeout=30))
            assert error["kind"] == "validation-error" and error["seq"] == 5
            # NaN in a JSON drag is named like any non-finite value, not malformed JSON
            ws.send(json.dumps({"handle_positions": [[float("nan")] * 3] * len(HANDLES)}))
            error = json.loads(ws.recv(timeout=30))
            assert error["kind"] == "validation-error" and error["seq"] == 6, error
            # A burst of drags: out-of-date ones are dropped, the latest always wins.
            for i in range(4, 40):
                ws.send(json.dumps({"handle_positions": targets[i].tolist(), "seq": i}))
            replies = []
            while not replies or replies[-1][0] != 39:
                replies.append(_reply(ws.recv(timeout=30)))
            seqs = [s for s, _ in replies]
            assert seqs == sorted(seqs) and len(seqs) < 36, seqs
            assert np.array_equal(replies[-1][1], want[39])
            for s, vertices in replies:
                assert np.array_equal(vertices, want[s])
            # Deleting the session closes the socket with 4404 after a problem message.
            assert http.delete(location).status_code == 204
            ws.send(targets[0].astype("<f4").tobytes())
            assert json.loads(ws.recv(timeout=30))["kind"] == "not-found"
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=30)
            assert closed.value.rcvd.code == 4404
        with connect(_ws_url(base, location), max_size=None) as ws:  # an unknown session
            assert json.loads(ws.recv(timeout=30))["status"] == 404
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=30)
            assert closed.value.rcvd.code == 4404
        metrics = http.get("/metrics").text
        assert 'ffs_session_solve_duration_seconds_count{transport="ws"}' in metrics
        assert "ffs_session_dropped_drags_total" in metrics
