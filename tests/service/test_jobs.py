"""Asynchronous jobs: submit, progress, result negotiation, cancel, failures, expiry."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest

import solver
from service.api.schemas import EXAMPLE_FORMS
from tests.helpers import DATA
from tests.helpers.meshes import icosphere, load
from tests.helpers.servers import running_app
from tests.helpers.service import debug_task, forms_json, mesh_json, problem


def wait_job(client, location, states=("succeeded", "failed", "cancelled"), timeout=60.0):
    """Poll a job until it reaches one of ``states``; returns (final status, polled docs)."""
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        doc = client.get(location).json()
        seen.append(doc)
        if doc["status"] in states:
            return doc, seen
        time.sleep(0.02)
    raise AssertionError(f"job did not reach {states}: {seen[-1]}")


def submit_debug(client, seconds=5.0, operation="deform", task="debug.sleep"):
    """Start a job that runs a test-only task (sleep or crash) through the job manager."""
    manager = client.app.state.services.backend.jobs
    job = client.portal.call(manager.submit,
                             debug_task(task, operation, seconds=seconds, steps=50))
    return job, f"/v1/jobs/{job.id}"


def test_job_lifecycle_json_and_glb(client):
    V, F = load("decimated-knight.off")
    forms = forms_json(V, F)
    response = client.post("/v1/jobs", json={"operation": "reconstruct",
                                             "input": {**forms, "options":
                                                       {"orthonormalize": True}}})
    assert response.status_code == 202, response.text
    location = response.headers["location"]
    first = response.json()
    assert location == f"/v1/jobs/{first['id']}" == first["links"]["self"]
    assert first["status"] in ("queued", "running")
    assert list(first["progress"]["stages"]) == ["validate", "assemble", "factorize", "solve",
                                                 "refine", "encode"]
    final, seen = wait_job(client, location)
    assert final["status"] == "succeeded", final
    assert final["progress"]["fraction"] == 1.0
    assert set(final["progress"]["stages"].values()) == {1.0}
    assert set(final["timings"]) >= {"queued", "validate", "assemble", "factorize", "solve"}
    assert final["finished_at"] and final["expires_at"] and final["error"] is None
    fractions = [doc["progress"]["fraction"] for doc in seen]
    assert fractions == sorted(fractions)  # progress never goes back

    result = client.get(f"{location}/result")
    assert result.status_code == 200 and result.headers["content-type"] == "application/json"
    want = solver.reconstruct(forms["faces"], forms["edges"], forms["lengths"], forms["angles"],
                              orthonormalize=True)
    np.testing.assert_allclose(result.json()["vertices"], want.vertices, atol=1e-9)
    glb = client.get(f"{location}/result", headers={"accept": "model/gltf-binary"})
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    gltf = client.get(f"{location}/result", headers={"accept": "model/gltf+json"})
    assert gltf.json()["asset"]["version"] == "2.0"
    problem(client.get(f"{location}/result", params={"color": "defect"}), 409,
            "color-not-computed")
    problem(client.get(f"{location}/result", params={"color": "distortion"}), 422,
            "unsupported-color")
    problem(client.get(f"{location}/result", headers={"accept": "text/csv"}), 406,
            "not-acceptable")

    assert client.delete(location).status_code == 204
    problem(client.get(location), 404, "not-found")


def test_job_with_precomputed_colour(client):
    V, F = icosphere(2)
    forms = forms_json(V, F)
    forms["angles"][0] += 0.1
    response = client.post("/v1/jobs", json={"operation": "reconstruct", "input": forms,
                                             "color": "defect"})
    location = response.headers["location"]
    assert wait_job(client, location)[0]["status"] == "succeeded"
    doc = client.get(f"{location}/result", params={"color": "defect"}).json()
    assert np.asarray(doc["colors"]).shape == (len(V), 4)
    assert "colors" not in client.get(f"{location}/result").json()
    glb = client.get(f"{location}/result", params={"color": "defect"},
                     headers={"accept": "model/gltf-binary"})
    assert b"COLOR_0" in glb.content[:4000]


def test_job_from_a_file_upload(client):
    data = (DATA / "face.off").read_bytes()
    response = client.post("/v1/jobs", data={"operation": "deform", "color": "distortion",
                                             "handles": json.dumps([
                                                 {"vertex": 0, "position": [0, 0, 0]},
                                                 {"vertex": 500, "position": [0, 0, 1]}])},
                           files={"file": ("face.off", data)})
    assert response.status_code == 202, response.text
    final, _ = wait_job(client, response.headers["location"])
    assert final["status"] == "succeeded" and final["operation"] == "deform"
    result = client.get(response.headers["location"] + "/result",
                        params={"color": "distortion"}).json()
    assert len(result["vertices"]) == 1180 and len(result["colors"]) == 1180


@pytest.mark.parametrize("operation", ["forms", "integrability", "parameterize",
                                       "interpolate"])
def test_jobs_for_every_operation(client, operation):
    from service.operations import OPERATIONS

    example = OPERATIONS[operation].request.model_config["json_schema_extra"]["examples"][0]
    response = client.post("/v1/jobs", json={"operation": operation, "input": example})
    final, _ = wait_job(client, response.headers["location"])
    assert final["status"] == "succeeded", final
    sync = client.post(f"/v1/{operation}", json=example).json()
    result = client.get(response.headers["location"] + "/result").json()
    for doc in (sync, result):  # reports hold timings
        doc.pop("report", None)
        for report in np.atleast_1d(doc.pop("refinement", [])):
            assert "refined" in report
    assert result == sync


def test_job_submission_errors(client):
    doc = problem(client.post("/v1/jobs", json={"operation": "explode", "input": {}}), 422,
                  "validation-error")
    assert doc["errors"][0]["field"] == "operation"
    bad = {**EXAMPLE_FORMS, "faces": [[0, 1]]}
    doc = problem(client.post("/v1/jobs", json={"operation": "reconstruct", "input": bad}),
                  422, "validation-error")
    assert doc["errors"][0]["field"] == "input.faces" and doc["errors"][0]["index"] == 0
    problem(client.post("/v1/jobs", json={"operation": "forms", "input": mesh_json(
        *icosphere(0)), "color": "defect"}), 422, "unsupported-color")
    problem(client.post("/v1/jobs", data={"operation": "forms"},
                        files={"file": ("x.txt", b"solid")}), 415, "unsupported-file-type")
    doc = problem(client.post("/v1/jobs", data={"color": "defect"},
                              files={"file": ("x.off", b"OFF")}), 422, "validation-error")
    assert doc["errors"][0]["field"] == "operation"
    problem(client.post("/v1/jobs", content=b"{", headers={"content-type": "application/json"}),
            400, "malformed-json")


def test_failed_job_reports_the_problem(client):
    lengths = list(EXAMPLE_FORMS["lengths"])
    lengths[0] = 5.0
    response = client.post("/v1/jobs", json={"operation": "reconstruct",
                                             "input": {**EXAMPLE_FORMS, "lengths": lengths}})
    final, _ = wait_job(client, response.headers["location"])
    assert final["status"] == "failed"
    error = final["error"]
    assert error["status"] == 422 and error["type"] == "/problems/triangle-inequality"
    assert error["errors"][0]["field"] == "faces"
    doc = problem(client.get(response.headers["location"] + "/result"), 409, "job-failed")
    assert doc["error"]["kind"] == "triangle-inequality"


def test_result_of_unfinished_job_and_cancel_running(client):
    executor = client.app.state.services.backend.executor
    job, location = submit_debug(client, seconds=30)
    doc, _ = wait_job(client, location, states=("running",))
    deadline = time.monotonic() + 10  # "running" comes with the dispatch, the stage follows
    while doc["progress"]["stage"] is None and time.monotonic() < deadline:
        time.sleep(0.02)
        doc = client.get(location).json()
    assert doc["progress"]["stage"] == "solve"
    response = problem(client.get(f"{location}/result"), 409, "job-not-finished")
    assert response["job_status"] == "running"
    pid = executor.running_pid(job.id)
    assert pid in executor.worker_pids()
    cancelled = client.delete(location)
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    problem(client.get(f"{location}/result"), 409, "job-cancelled")
    _wait_pool(client, 2)
    assert pid not in executor.worker_pids()  # the running solve was stopped with its worker
    assert client.post("/v1/forms", json=mesh_json(*icosphere(1))).status_code == 200


def _wait_pool(client, workers, timeout=30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        doc = client.get("/readyz").json()
        if doc["workers_ready"] == workers and doc["busy"] == 0:
            return
        time.sleep(0.05)
    raise AssertionError(client.get("/readyz").json())


def test_worker_death_fails_the_job_and_the_service_keeps_serving(client):
    executor = client.app.state.services.backend.executor
    # A worker that exits on its own.
    _, location = submit_debug(client, task="debug.crash")
    final, _ = wait_job(client, location)
    assert final["status"] == "failed"
    assert final["error"]["kind"] == "worker-died"
    assert "exit code 3" in final["error"]["detail"]
    # A worker killed from outside (e.g. by the OOM killer) while it runs a job.
    job, location = submit_debug(client, seconds=30)
    wait_job(client, location, states=("running",))
    os.kill(executor.running_pid(job.id), signal.SIGKILL)
    final, _ = wait_job(client, location)
    assert final["status"] == "failed" and "SIGKILL" in final["error"]["detail"]
    _wait_pool(client, 2)
    V, F = icosphere(1)
    assert client.post("/v1/forms", json=mesh_json(V, F)).status_code == 200
    assert client.post("/v1/reconstruct", json=forms_json(V, F)).status_code == 200


def test_queued_job_cancel_keeps_the_running_worker():
    with running_app(workers=1) as c:
        executor = c.app.state.services.backend.executor
        running, running_at = submit_debug(c, seconds=30)
        wait_job(c, running_at, states=("running",))
        pid = executor.running_pid(running.id)
        _, queued_at = submit_debug(c, seconds=30)
        assert c.get(queued_at).json()["status"] == "queued"
        assert c.get("/readyz").json()["queue_depth"] == 1
        assert c.delete(queued_at).json()["status"] == "cancelled"
        assert executor.running_pid(running.id) == pid
        assert c.delete(running_at).json()["status"] == "cancelled"


def test_job_timeout_ttl_and_store_limit():
    # FFS_JOB_TIMEOUT counts from submission, and the job after the timed-out one waits for
    # the replacement of the worker that was stopped: 3 s lets a loaded machine start it
    # (0.5 s did not, at load 16); a TTL of 2 s lets its polls see a finished job.
    with running_app(workers=1, job_timeout=3.0, job_ttl=2.0, max_jobs=2) as c:
        _, location = submit_debug(c, seconds=30)
        final, _ = wait_job(c, location)
        assert final["status"] == "failed" and final["error"]["kind"] == "timeout"
        ok = c.post("/v1/jobs", json={"operation": "forms",
                                      "input": mesh_json(*icosphere(0))})
        ok_at = ok.headers["location"]
        done = wait_job(c, ok_at)[0]
        assert done["status"] == "succeeded", done
        # The store is full of finished jobs: the oldest one gives way to the new job.
        third = c.post("/v1/jobs", json={"operation": "forms", "input": mesh_json(*icosphere(0))})
        assert third.status_code == 202, third.text
        problem(c.get(location), 404, "not-found")
        time.sleep(2.6)  # both jobs expire (TTL 2 s); the sweeper removes them
        problem(c.get(ok_at), 404, "not-found")
        assert c.post("/v1/jobs", json={"operation": "forms",
                                        "input": mesh_json(*icosphere(0))}).status_code == 202


def test_progress_is_honest_when_the_solver_goes_back_to_factorize():
    from service.backends.jobs import Job

    V, F = icosphere(2)
    forms = solver.fundamental_forms(V, F)
    job, seen = Job(id="x", operation="reconstruct"), []

    def progress(stage: str, fraction: float) -> None:
        job.update_progress(stage, fraction)
        seen.append((stage, dict(job.stages)))

    # The orthonormalization (Sec. 4) factorizes again after the first solve.
    result = solver.reconstruct(forms.faces, forms.edges, forms.lengths, forms.angles * 0.8,
                                orthonormalize=True, refine=False, progress=progress)
    assert result.report["solve_path"] == "factorization"
    order = [stage for stage, _ in seen]
    assert "factorize" in order[order.index("solve"):], order  # it did go back
    for stage, stages in seen:
        if stage == "factorize":
            assert stages["factorize"] < 1.0 and stages["solve"] == 0.0, (stage, stages)
    assert job.stages["solve"] == 1.0 and job.stages["factorize"] == 1.0
