"""Ownership across replicas (issue 46): two real uvicorn replicas with the same API keys
on one Dask cluster (FFS_EXECUTOR=dask). A job or session of one key, created through one
replica, is 404 for another key through the other replica (HTTP and WebSocket), served to
its owner and to an admin key there, and counted against its key's quota cluster-wide; a
job's webhook is delivered, signed, from the cluster."""

from __future__ import annotations

import json
import time

import dask
import httpx
import numpy as np
import pytest
from distributed import LocalCluster

from tests.helpers.meshes import icosphere
from tests.helpers.servers import uvicorn_process
from tests.helpers.service import problem

KEYS = {"alice": "alice-dask-key-0123456789", "bob": "bob-dask-key-0123456789",
        "ops": "ops-dask-key-0123456789"}
HANDLES = [0, 40, 80, 120]


@pytest.fixture(scope="module")
def receiver():
    from tests.service.test_webhooks import Receiver

    found = Receiver()
    yield found
    found.close()


@pytest.fixture(scope="module")
def replicas(receiver):
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}), LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address=":0", worker_dashboard_address=None) as cluster:
        env = {"FFS_EXECUTOR": "dask", "FFS_DASK_SCHEDULER_ADDRESS": cluster.scheduler_address,
               "FFS_WORKERS": "2", "FFS_API_KEYS": json.dumps(KEYS), "FFS_ADMIN_KEYS": "ops",
               "FFS_KEY_CONCURRENT_SESSIONS": "1",
               "FFS_WEBHOOK_HOSTS": f"127.0.0.1:{receiver.port}"}
        with uvicorn_process(env) as (a, _), uvicorn_process(env) as (b, _):
            yield a, b


def _as(base: str, name: str) -> httpx.Client:
    return httpx.Client(base_url=base, timeout=120,
                        headers={"Authorization": f"Bearer {KEYS[name]}"})


def test_jobs_and_sessions_belong_to_their_key_on_every_replica(replicas):
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    a, b = replicas
    V, F = icosphere(3)
    with _as(a, "alice") as alice_a, _as(b, "alice") as alice_b, _as(b, "bob") as bob_b, \
            _as(b, "ops") as ops_b:
        job = alice_a.post("/v1/jobs", json={"operation": "forms", "input": {
            "vertices": V.tolist(), "faces": F.tolist()}})
        assert job.status_code == 202, job.text
        location = job.headers["location"]
        deadline = time.monotonic() + 120
        while alice_b.get(location).json()["status"] in ("queued", "running"):
            assert time.monotonic() < deadline
            time.sleep(0.1)
        for method, path in (("GET", location), ("GET", f"{location}/result"),
                             ("DELETE", location)):
            problem(bob_b.request(method, path), 404, "not-found")
        assert alice_b.get(f"{location}/result").status_code == 200
        job_id = location.rsplit("/", 1)[1]
        assert job_id in [j["id"] for j in ops_b.get("/v1/jobs").json()]
        assert job_id not in [j["id"] for j in bob_b.get("/v1/jobs").json()]
        assert ops_b.get(f"{location}/result").status_code == 200  # the admin fetches it
        assert ops_b.delete(location).status_code == 204  # and deletes it, for every replica
        problem(alice_a.get(location), 404, "not-found")

        created = alice_a.post("/v1/sessions", json={
            "vertices": V.tolist(), "faces": F.tolist(),
            "handles": [{"vertex": h} for h in HANDLES]})
        assert created.status_code == 201, created.text
        session = created.headers["location"]
        drag = {"handle_positions": V[HANDLES].tolist()}
        problem(bob_b.post(f"{session}/solve", json=drag), 404, "not-found")
        problem(bob_b.get(session), 404, "not-found")
        problem(bob_b.delete(session), 404, "not-found")
        assert alice_b.post(f"{session}/solve", json=drag).status_code == 200
        session_id = session.rsplit("/", 1)[1]
        assert session_id in [x["id"] for x in ops_b.get("/v1/sessions").json()]
        assert session_id in [x["id"] for x in alice_b.get("/v1/sessions").json()]
        assert session_id not in [x["id"] for x in bob_b.get("/v1/sessions").json()]
        assert ops_b.post(f"{session}/solve", json=drag).status_code == 200
        url = b.replace("http://", "ws://") + session + "/ws"
        with connect(url, subprotocols=["ffs", f"bearer.{KEYS['bob']}"]) as ws:
            assert json.loads(ws.recv(timeout=30))["status"] == 404
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=10)
        with connect(url, max_size=None, subprotocols=["ffs", f"bearer.{KEYS['alice']}"]) as ws:
            ws.send(np.asarray(V[HANDLES], dtype="<f4").tobytes())
            assert len(ws.recv(timeout=60)) >= len(V) * 12
        # The key's session quota (1) counts across replicas: a second one on B is refused.
        second = alice_b.post("/v1/sessions", json={
            "vertices": V.tolist(), "faces": F.tolist(),
            "handles": [{"vertex": h} for h in HANDLES]})
        doc = problem(second, 429, "quota-exceeded")
        assert doc["quota"] == "concurrent-sessions"
        assert second.headers["ratelimit-policy"].startswith('"concurrent-sessions";q=1')
        assert ops_b.delete(session).status_code == 204
        problem(alice_a.get(session), 404, "not-found")


def test_a_job_on_the_cluster_calls_its_webhook(replicas, receiver):
    from service.access.keys import derived_webhook_secret
    from service.access.webhooks import signature

    a, b = replicas
    V, F = icosphere(2)
    with _as(a, "alice") as alice_a, _as(b, "alice") as alice_b:
        job = alice_a.post("/v1/jobs", json={
            "operation": "forms", "input": {"vertices": V.tolist(), "faces": F.tolist()},
            "callback_url": f"http://127.0.0.1:{receiver.port}/dask"})
        assert job.status_code == 202, job.text
        [delivery] = receiver.wait("/dask", 1)
        assert json.loads(delivery["body"]) == alice_b.get(job.headers["location"]).json()
        header = delivery["headers"]["X-FFS-Signature"]
        stamp = int(header.split(",")[0].removeprefix("t="))
        assert header == signature(derived_webhook_secret(KEYS["alice"]), stamp,
                                   delivery["body"])
