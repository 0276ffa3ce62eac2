"""Health, readiness, metrics, the problem catalogue, CORS and settings."""

from __future__ import annotations

import pytest
from starlette.testclient import TestClient

from service.api.problems import PROBLEM_KINDS
from service.app import create_app
from service.settings import Settings
from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app
from tests.helpers.service import mesh_json


def test_healthz_and_readyz(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    doc = ready.json()
    assert doc["status"] == "ready" and doc["workers"] == 2 and doc["workers_ready"] == 2


def test_readyz_is_503_without_a_pool():
    app = create_app(Settings(workers=1))
    plain = TestClient(app)  # no lifespan: the pool never starts
    assert plain.get("/healthz").status_code == 200
    response = plain.get("/readyz")
    assert response.status_code == 503 and response.json()["status"] == "unavailable"
    assert plain.post("/v1/forms", json=mesh_json(*icosphere(0))).status_code == 503


def test_metrics(client):
    client.post("/v1/forms", json=mesh_json(*icosphere(1)))
    client.post("/v1/reconstruct", json={"faces": [[0, 1, 2]]})  # 422
    client.get("/v1/jobs/0123456789abcdef0123456789abcdef")
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text
    assert 'ffs_http_requests_total{method="POST",route="/v1/forms",status="200"}' in text
    assert 'ffs_http_requests_total{method="POST",route="/v1/reconstruct",status="422"}' in text
    assert 'route="/v1/jobs/{job_id}",status="404"' in text  # templated, not per id
    assert 'ffs_http_request_duration_seconds_bucket{le="0.005",method="POST",' \
           'route="/v1/forms"}' in text
    assert 'ffs_solver_stage_duration_seconds_count{operation="forms",stage="solve"}' in text
    for name in ("ffs_queue_depth", "ffs_pool_size 2.0", "ffs_pool_busy_workers",
                 "ffs_pool_ready_workers 2.0", "ffs_worker_restarts", "ffs_jobs{status="):
        assert name in text


def test_problem_catalogue(client):
    kinds = client.get("/problems").json()
    assert {k["kind"] for k in kinds} == set(PROBLEM_KINDS)
    one = client.get("/problems/index-out-of-range").json()
    assert one == {"type": "/problems/index-out-of-range", "kind": "index-out-of-range",
                   "status": 422, "title": "Index out of range",
                   "description": "An index (vertex, face, edge) is negative or not below "
                                  "the element count."}


def test_cors(client):
    with running_app(workers=1, cors_origins=["https://viewer.example"]) as c:
        preflight = c.options("/v1/forms", headers={
            "origin": "https://viewer.example", "access-control-request-method": "POST",
            "access-control-request-headers": "content-type"})
        assert preflight.status_code == 200
        assert preflight.headers["access-control-allow-origin"] == "https://viewer.example"
        response = c.post("/v1/jobs", json={"operation": "forms",
                                            "input": mesh_json(*icosphere(0))},
                          headers={"origin": "https://viewer.example"})
        assert response.headers["access-control-allow-origin"] == "https://viewer.example"
        assert "location" in response.headers["access-control-expose-headers"].lower()
        other = c.get("/healthz", headers={"origin": "https://evil.example"})
        assert "access-control-allow-origin" not in other.headers
    # CORS off by default: the shared app's default settings (no second app to start)
    assert "access-control-allow-origin" not in client.get(
        "/healthz", headers={"origin": "https://viewer.example"}).headers


def test_settings_from_environment(monkeypatch):
    monkeypatch.setenv("FFS_WORKERS", "3")
    monkeypatch.setenv("FFS_QUEUE_SIZE", "7")
    monkeypatch.setenv("FFS_MAX_VERTICES", "1000")
    monkeypatch.setenv("FFS_REQUEST_TIMEOUT", "2.5")
    monkeypatch.setenv("FFS_JOB_TTL", "60")
    monkeypatch.setenv("FFS_SOLVER_BACKEND", "superlu")
    monkeypatch.setenv("FFS_CORS_ORIGINS", "https://a.example, https://b.example")
    settings = Settings()
    assert (settings.workers, settings.queue_size, settings.max_vertices) == (3, 7, 1000)
    assert settings.request_timeout == 2.5 and settings.job_ttl == 60.0
    assert settings.solver_backend == "superlu"
    assert settings.cors_origins == ["https://a.example", "https://b.example"]
    monkeypatch.setenv("FFS_CORS_ORIGINS", '["*"]')
    assert Settings().cors_origins == ["*"]
    monkeypatch.setenv("FFS_WORKERS", "0")
    with pytest.raises(ValueError):
        Settings()


def test_default_backend_setting_is_used():
    with running_app(workers=1, solver_backend="superlu") as c:
        from service.api.schemas import EXAMPLE_FORMS

        direct = {"exact_shortcut": False}  # exact forms would skip the factorization
        doc = c.post("/v1/reconstruct", json={**EXAMPLE_FORMS, "options": direct}).json()
        assert doc["report"]["backend"] == "superlu"
        doc = c.post("/v1/reconstruct", json={**EXAMPLE_FORMS,
                                              "options": {"solver": "auto", **direct}}).json()
        from solver.linalg import default_backend

        assert doc["report"]["backend"] == default_backend()
