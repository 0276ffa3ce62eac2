"""The Dask backend (FFS_EXECUTOR=dask) on a real cluster: a LocalCluster with two worker
processes on loopback and two service instances on it. Jobs submitted on one replica are
polled, fetched and cancelled on the other; a worker killed mid-job makes the cluster retry
the job; a task whose workers keep dying fails with the reason; results equal the local
executor's to the last bit; sessions live in Dask actors. The registry logic (job and
session records in the scheduler) is also tested on its own, without a cluster.
"""

from __future__ import annotations

import json
import os
import pickle
import signal
import struct
import time

import dask
import numpy as np
import pytest
from distributed import Client, LocalCluster
from distributed.scheduler import KilledWorker

from service.backends.dask.registry import Registry
from service.backends.jobs import Job
from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app
from tests.helpers.service import debug_task, forms_json, problem
from tests.helpers.sessions import reference_solves, rotation_z

HANDLES = [0, 40, 80, 120]
GROUP = list(range(500, 506))


@pytest.fixture(scope="module")
def cluster():
    """Scheduler + 2 single-threaded worker processes on loopback; one retry per task
    whose worker dies (distributed.scheduler.allowed-failures = 1)."""
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}), LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address=":0", worker_dashboard_address=None) as c:
        yield c


@pytest.fixture(scope="module")
def inspector(cluster):
    """A plain client of the test, to find and kill worker processes."""
    with Client(cluster, set_as_default=False) as c:
        yield c


@pytest.fixture(scope="module")
def replicas(cluster):
    """Two service instances (in-process apps) on the same cluster."""
    address = cluster.scheduler_address
    with running_app(executor="dask", dask_scheduler_address=address, job_ttl=60) as a, \
            running_app(executor="dask", dask_scheduler_address=address, job_ttl=60) as b:
        yield a, b


def wait_job(client, location, states=("succeeded", "failed", "cancelled"), timeout=120.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        doc = client.get(location).json()
        if doc["status"] in states:
            return doc
        time.sleep(0.05)
    raise AssertionError(f"job did not reach {states}: {doc}")


def wait_workers(client, count=2, timeout=180.0):
    """Until ``count`` workers are ready (a killed worker's nanny starts a new one: numpy,
    scipy, MKL and the service's preload; seen to take over 60 s on a loaded 2-core VM)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if client.get("/readyz").json()["workers_ready"] >= count:
            return
        time.sleep(0.1)
    raise AssertionError(client.get("/readyz").json())


def _kill_worker(inspector, address):
    os.kill(inspector.run(os.getpid)[address], signal.SIGKILL)


def _kill_worker_of(inspector, key, timeout=60.0):
    """SIGKILL the worker process that runs ``key``; returns its address."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        where = [a for a, keys in inspector.processing().items() if key in keys]
        if where:
            _kill_worker(inspector, where[0])
            return where[0]
        time.sleep(0.02)
    raise AssertionError(f"{key} never reached a worker")


def test_readiness_and_settings_aliases(replicas, monkeypatch):
    a, _ = replicas
    ready = a.get("/readyz").json()
    assert ready["status"] == "ready" and ready["workers_ready"] == 2 and ready["workers"] == 2
    from service.settings import Settings

    monkeypatch.setenv("SOLVER_EXECUTOR", "dask")
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", "tcp://scheduler:8786")
    settings = Settings()
    assert settings.executor == "dask"
    assert settings.dask_scheduler_address == "tcp://scheduler:8786"
    monkeypatch.setenv("FFS_EXECUTOR", "process")
    assert Settings().executor == "local"  # the prefixed name wins; process = local
    monkeypatch.delenv("FFS_EXECUTOR")
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS")
    with pytest.raises(ValueError, match="FFS_DASK_SCHEDULER_ADDRESS"):
        Settings()


def test_job_on_one_replica_is_polled_and_fetched_on_the_other(replicas, client):
    a, b = replicas
    V, F = icosphere(3)
    body = {**forms_json(V, F), "options": {"orthonormalize": True}}
    local = np.asarray(client.post("/v1/reconstruct", json=body).json()["vertices"])

    submitted = a.post("/v1/jobs", json={"operation": "reconstruct", "input": body})
    assert submitted.status_code == 202, submitted.text
    location = submitted.headers["location"]
    final = wait_job(b, location)
    assert final["status"] == "succeeded", final
    assert final["progress"]["fraction"] == 1.0
    assert set(final["timings"]) >= {"queued", "validate", "assemble", "solve"}
    result = b.get(f"{location}/result")
    assert result.status_code == 200
    assert np.array_equal(np.asarray(result.json()["vertices"]), local)  # to the last bit
    glb = a.get(f"{location}/result", headers={"accept": "model/gltf-binary"})
    assert glb.content[:4] == b"glTF"
    sync = b.post("/v1/reconstruct", json=body)
    assert np.array_equal(np.asarray(sync.json()["vertices"]), local)
    assert b.delete(location).status_code == 204
    problem(a.get(location), 404, "not-found")


def test_failed_and_cancelled_jobs_across_replicas(replicas):
    a, b = replicas
    bad = a.post("/v1/jobs", json={"operation": "reconstruct", "input": {
        "faces": [[0, 1, 2]], "edges": [[0, 1], [0, 2], [1, 2]],
        "lengths": [1.0, 1.0, 5.0], "angles": [0.0, 0.0, 0.0]}})
    final = wait_job(b, bad.headers["location"])
    assert final["status"] == "failed" and final["error"]["kind"] == "triangle-inequality"
    doc = problem(b.get(bad.headers["location"] + "/result"), 409, "job-failed")
    assert doc["error"]["status"] == 422

    manager = a.app.state.services.backend.jobs
    job = a.portal.call(manager.submit,
                        debug_task("debug.sleep", "deform", seconds=2.0, steps=40))
    location = f"/v1/jobs/{job.id}"
    running = wait_job(b, location, states=("running",))
    deadline = time.monotonic() + 10
    while running["progress"]["stage"] != "solve" and time.monotonic() < deadline:
        running = b.get(location).json()
    assert running["progress"]["stage"] == "solve"  # progress travels through the scheduler
    cancelled = b.delete(location)
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    assert a.get(location).json()["status"] == "cancelled"
    problem(a.get(f"{location}/result"), 409, "job-cancelled")
    assert a.delete(location).status_code == 204


def test_worker_killed_during_a_large_job_is_retried(replicas, client, inspector):
    a, b = replicas
    V, F = icosphere(5)  # 20 480 faces, forms flattened by 2 %: a least-squares solve
    body = forms_json(V, F)  # (factorization) of about a second in a worker
    body["angles"] = [0.98 * a for a in body["angles"]]
    body["options"] = {"orthonormalize": True}
    submitted = a.post("/v1/jobs", json={"operation": "reconstruct", "input": body})
    location = submitted.headers["location"]
    job_id = submitted.json()["id"]
    wait_job(b, location, states=("running",))
    killed = _kill_worker_of(inspector, f"ffs-job-{job_id}")
    final = wait_job(b, location)
    assert final["status"] == "succeeded", final  # the cluster ran it again elsewhere
    local = np.asarray(client.post("/v1/reconstruct", json=body).json()["vertices"])
    fetched = np.asarray(a.get(f"{location}/result").json()["vertices"])
    assert np.array_equal(fetched, local)
    wait_workers(a)
    assert killed  # and the service kept serving:
    assert b.post("/v1/forms", json={"vertices": V[:3].tolist(),
                                     "faces": [[0, 1, 2]]}).status_code == 200


def test_a_task_whose_workers_keep_dying_fails_with_the_reason(replicas):
    a, b = replicas
    manager = a.app.state.services.backend.jobs
    job = a.portal.call(manager.submit, debug_task("debug.crash", "deform", code=3))
    final = wait_job(b, f"/v1/jobs/{job.id}", timeout=120)
    assert final["status"] == "failed"
    assert final["error"]["kind"] == "worker-died"
    assert "died 2 times" in final["error"]["detail"]
    wait_workers(a)
    wait_workers(b)


def test_session_on_a_dask_actor_used_from_both_replicas(replicas):
    a, b = replicas
    V, F = icosphere(3)
    created = a.post("/v1/sessions", json={
        "vertices": V.tolist(), "faces": F.tolist(),
        "handles": [{"vertex": h} for h in HANDLES], "rotations": [{"faces": GROUP}]})
    assert created.status_code == 201, created.text
    doc = created.json()
    assert doc["executor"] == "dask" and doc["n_rotation_groups"] == 1
    location = created.headers["location"]
    rng = np.random.default_rng(3)
    targets = V[HANDLES][None] + rng.integers(-32, 32, size=(5, len(HANDLES), 3)) / 256.0
    rotations = np.stack([rotation_z(0.1 * i)[None] for i in range(5)])
    want = reference_solves(V, F, HANDLES, targets, groups=[GROUP], rotations=rotations)
    for i in range(5):
        side = (a, b)[i % 2]
        r = side.post(f"{location}/solve", json={"handle_positions": targets[i].tolist(),
                                                 "handle_rotations": rotations[i].tolist()})
        assert r.status_code == 200, r.text
        assert np.array_equal(np.asarray(r.json()["vertices"]), want[i]), i
    with b.websocket_connect(f"{location}/ws") as ws:
        ws.send_text(json.dumps({"handle_positions": targets[4].tolist(),
                                 "handle_rotations": rotations[4].tolist(), "seq": 9}))
        message = ws.receive_bytes()
        assert struct.unpack("<II", message[:8]) == (9, len(V))
        assert np.array_equal(np.frombuffer(message[8:], "<f4").reshape(-1, 3),
                              want[4].astype(np.float32))
    assert b.get(location).json()["id"] == doc["id"]
    assert b.delete(location).status_code == 204
    problem(a.get(location), 404, "not-found")


def test_session_limits_and_worker_death_on_dask(replicas, inspector):
    a, b = replicas
    V, F = icosphere(2)
    body = {"vertices": V.tolist(), "faces": F.tolist(),
            "handles": [{"vertex": h} for h in HANDLES]}
    sessions = a.app.state.services.backend.sessions
    sessions.policy.max_sessions = 1
    try:
        first = a.post("/v1/sessions", json=body)
        assert first.status_code == 201
        problem(a.post("/v1/sessions", json=body), 429, "too-many-sessions")
        sessions.policy.max_sessions = 8
        sessions.policy.max_memory = 1024
        problem(a.post("/v1/sessions", json=body), 503, "session-memory")
    finally:
        sessions.policy.max_sessions, sessions.policy.max_memory = 8, 4 * 1024**3
    location = first.headers["location"]
    target = {"handle_positions": V[HANDLES].tolist()}
    assert b.post(f"{location}/solve", json=target).status_code == 200
    record = a.portal.call(sessions.connection.call, "session_get", first.json()["id"])
    _kill_worker(inspector, record["worker"])  # the worker holding the session's actor
    started = time.monotonic()
    doc = problem(b.post(f"{location}/solve", json=target), 410, "session-gone")
    assert time.monotonic() - started < 15  # never hangs
    assert "worker" in doc["reason"]
    problem(a.get(location), 410, "session-gone")
    wait_workers(a)
    again = a.post("/v1/sessions", json=body)  # the service keeps serving sessions
    assert again.status_code == 201
    assert a.post(again.headers["location"] + "/solve", json=target).status_code == 200
    assert a.delete(again.headers["location"]).status_code == 204


# ----------------------------------------------------------- the registry on its own


def _job(registry, now=1000.0, **meta):
    job = Job(id="j1", operation="reconstruct", created_at=now)
    record = {name: getattr(job, name) for name in ("id", "operation", "color", "status",
                                                    "created_at", "stages")}
    registry.job_add(record, {"key": "ffs-job-j1", "ttl": 10.0, "timeout": 100.0, **meta},
                     max_jobs=2, now=now)
    return registry.jobs["j1"]


def test_registry_follows_job_tasks():
    registry = Registry()
    job = _job(registry)
    registry.transition("ffs-job-j1", "queued", "processing", stimulus_id="s")
    assert job.status == "running"
    registry.log_event("ffs-job", {"id": "j1", "stage": "factorize", "fraction": 0.5})
    assert job.stage == "factorize" and job.stages["assemble"] == 1.0
    registry.transition("ffs-job-j1", "processing", "memory", stimulus_id="s")
    assert job.status == "succeeded" and job.fraction == 1.0
    assert registry.job_get("j1", job.expires_at - 1)["status"] == "succeeded"
    assert registry.job_get("j1", job.expires_at + 1) is None
    assert registry.job_sweep(job.expires_at + 1)["expired"] == ["j1"]

    job = _job(registry)  # a failure reported by the task itself
    registry.log_event("ffs-job", {"id": "j1", "error": {"kind": "not-integrable"}})
    registry.transition("ffs-job-j1", "processing", "memory", stimulus_id="s")
    assert job.status == "failed" and job.error == {"kind": "not-integrable"}
    registry.job_remove("j1")

    job = _job(registry)  # its workers kept dying
    killed = pickle.dumps(KilledWorker("ffs-job-j1", "tcp://10.0.0.1:1", 1))
    registry.transition("ffs-job-j1", "processing", "erred", exception=killed,
                        stimulus_id="s")
    assert job.status == "failed" and job.error["kind"] == "worker-died"
    assert "died 2 times" in job.error["detail"] and "retried it 1 time" in job.error["detail"]
    registry.job_remove("j1")

    job = _job(registry)  # released by every client before it ran
    registry.transition("ffs-job-j1", "released", "forgotten", stimulus_id="s")
    assert job.status == "cancelled"
    registry.job_remove("j1")

    job = _job(registry)  # running too long
    swept = registry.job_sweep(job.created_at + 101)
    assert swept["timed_out"] == ["j1"] and job.error["kind"] == "timeout"
    _job(registry, now=2000.0)
    registry.jobs["j2"] = registry.jobs["j1"]
    assert registry.job_add({"id": "j3", "operation": "forms"}, {"key": "k3", "ttl": 1,
                                                                 "timeout": 1}, 2, 2000.0) == 2


def test_registry_admits_expires_and_buries_sessions():
    registry = Registry()
    assert registry.session_admit("s1", 100, 2, 1000, 0.0, 60.0, 5.0) is None
    assert registry.session_ready("s1", {"handles": [0]}, 300, "tcp://w1", 0.0, 1000) is None
    assert registry.session_admit("s2", 800, 2, 1000, 0.0, 60.0, 5.0) == {"kind": "memory",
                                                                         "used": 300}
    assert registry.session_admit("s2", 100, 2, 1000, 0.0, 60.0, 5.0) is None
    assert registry.session_admit("s3", 100, 2, 1000, 0.0, 60.0, 5.0)["kind"] == "too-many"
    assert registry.session_ready("s2", {}, 900, "tcp://w2", 0.0, 1000) == {"kind": "memory",
                                                                          "used": 300}
    assert registry.session_get("s2") is None
    registry.session_touch("s1", 4.0, 3)
    swept = registry.session_sweep(6.0, 5.0)
    assert swept["release"] == [] and swept["count"] == 1 and swept["memory"] == 300
    assert registry.session_get("s1")["solves"] == 3
    swept = registry.session_sweep(9.5, 5.0)  # idle for 5.5 s > TTL
    assert swept["release"] == ["s1"] and registry.session_get("s1")["state"] == "gone"
    assert "FFS_SESSION_TTL" in registry.session_get("s1")["reason"]
    assert registry.session_sweep(20.0, 5.0)["gone"] == []  # the tombstone is dropped
    assert registry.session_admit("s4", 100, 2, 1000, 20.0, 60.0, 5.0) is None
    registry.session_ready("s4", {}, 100, "tcp://w1", 20.0, 1000)
    registry.remove_worker(scheduler=None, worker="tcp://w1", stimulus_id="s")
    assert registry.session_get("s4")["state"] == "gone"
    assert "left the cluster" in registry.session_get("s4")["reason"]
    assert registry.session_remove("s4")["id"] == "s4"
