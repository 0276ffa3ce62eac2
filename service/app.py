"""The FastAPI application: ``create_app(settings)`` and the module-level ``app``.

Serve with ``uvicorn service.app:app --host 0.0.0.0 --port 8000`` or ``python -m service``.
The worker pool starts in the lifespan (``/readyz`` turns 200 when a worker is up) and stops
with it. ``FFS_EXECUTOR`` picks the backend of the pool, the jobs and the sessions: ``local``
(processes of this service, jobs in memory) or ``dask`` (a Dask cluster shared by every
replica; :mod:`service.cluster`).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware
from starlette.middleware.gzip import GZipMiddleware

from service import openapi
from service.executor import make_executor
from service.jobs import JobManager, MemoryJobStore
from service.metrics import MetricsMiddleware, ServiceMetrics
from service.problems import install_handlers
from service.routes import health, jobs, operations, sessions, web
from service.sessions import make_sessions
from service.settings import Settings

VERSION = "1.0.0"
DESCRIPTION = """\
Reconstruct and deform triangle meshes from their discrete fundamental forms (edge lengths
and signed dihedral angles).

* Every mesh input is JSON (`vertices`, `faces`) or a multipart upload of an OBJ, PLY, OFF,
  STL or GLB file in `file`; vertex order is kept.
* Mesh results negotiate `Accept`: `application/json` (default), `model/gltf-binary`,
  `model/gltf+json`; `?color=defect|distortion` adds a vertex colour ramp.
* Errors are RFC 9457 `application/problem+json` documents with `errors` pointers
  (`GET /problems` lists the types).
* Long work: `POST /v1/jobs` -> 202 + Location, poll `GET /v1/jobs/{id}`, fetch
  `GET /v1/jobs/{id}/result`, cancel with `DELETE`.
* Interactive deformation: `POST /v1/sessions` factorizes once (201 + Location); each drag is
  `POST /v1/sessions/{id}/solve` (JSON, GLB, glTF or raw float32 vertices) or a message on
  the WebSocket `/v1/sessions/{id}/ws` (docs/service.md describes its binary format).
"""

TAGS = [
    {"name": "operations", "description": "Synchronous solver operations."},
    {"name": "jobs", "description": "Asynchronous jobs with progress."},
    {"name": "sessions", "description": "Interactive deformation: factorize once, solve per "
                                        "drag (HTTP or WebSocket)."},
    {"name": "health", "description": "Liveness, readiness, metrics, problem types."},
]


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app (the worker pool starts with the lifespan, not here)."""
    settings = settings or Settings()
    logging.getLogger("service").setLevel(settings.log_level.upper())
    metrics = ServiceMetrics()

    def on_job_finished(operation: str, result: dict[str, Any]) -> None:
        metrics.observe_task(operation, result, "ok")

    manager: Any
    if settings.executor == "dask":
        from service.cluster import make_backend

        executor, manager, session_backend = make_backend(settings)
        manager._on_result = on_job_finished
    else:
        executor = make_executor(settings)
        manager = JobManager(MemoryJobStore(), executor, ttl=settings.job_ttl,
                             timeout=settings.job_timeout, max_jobs=settings.max_jobs,
                             on_result=on_job_finished)
        session_backend = make_sessions(settings)
    metrics.bind(executor, manager.counts)
    metrics.bind_sessions(session_backend)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await executor.start()
        await manager.start()
        await session_backend.start()
        app.state.started = True
        try:
            yield
        finally:
            app.state.started = False
            await session_backend.stop()
            await manager.stop()
            await executor.shutdown()

    app = FastAPI(title="Fundamental forms service", version=VERSION, description=DESCRIPTION,
                  lifespan=lifespan, openapi_tags=TAGS, separate_input_output_schemas=False)
    app.state.settings = settings
    app.state.executor = executor
    app.state.jobs = manager
    app.state.sessions = session_backend
    app.state.metrics = metrics
    app.state.started = False
    install_handlers(app)
    app.include_router(operations.router)
    app.include_router(jobs.router)
    app.include_router(sessions.router)
    app.include_router(health.router)
    app.include_router(web.router)
    app.mount("/static", web.static_files(), name="static")

    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(GZipMiddleware, minimum_size=settings.gzip_minimum_size,
                       compresslevel=settings.gzip_level)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["*"], allow_headers=["*"],
                           expose_headers=["Location", "Retry-After", "Server-Timing"])

    def custom_openapi() -> dict[str, Any]:
        return openapi.build(app)

    app.openapi = custom_openapi  # type: ignore[method-assign]
    return app


app = create_app()
