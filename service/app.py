"""The FastAPI application: ``create_app(settings)`` and the module-level ``app``.

Serve with ``python -m service`` (or ``uvicorn service.app:app``). The backend
(``FFS_EXECUTOR``: ``local`` processes of this service, or ``dask``, a cluster shared by
every replica; :mod:`service.backends`) and the parser process of large bodies
(:class:`~service.http.bodies.ParserPool`) start in the lifespan (``/readyz`` turns 200 when
a worker is up) and stop with it. Routes get it through typed dependencies
(:mod:`service.http.dependencies`).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware

from service.api.task import TaskResult
from service.backends import make_backend
from service.http import openapi
from service.http.auth import Access, AuthMiddleware, declare_bearer
from service.http.compression import ParallelGZipMiddleware
from service.http.dependencies import Services
from service.http.metrics import MetricsMiddleware, ServiceMetrics
from service.http.origins import OriginMiddleware
from service.http.problems import install_handlers
from service.http.routes import access, docs, health, jobs, operations, sessions, web
from service.http.security import SecurityHeadersMiddleware
from service.logs import configure_access_log, configure_logging
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
    """Build the app; its backend and parser process start with the lifespan, not here.

    Args:
        settings: The settings; by default read from the environment (``FFS_*``).

    Returns:
        The application, its :class:`~service.http.dependencies.Services` on
        ``app.state.services``.
    """
    settings = settings or Settings()
    configure_logging(settings.log_level)
    configure_access_log(settings.access_log_static)
    metrics = ServiceMetrics()

    def on_job_finished(operation: str, result: TaskResult) -> None:
        metrics.observe_task(operation, result, "ok")

    services = Services(settings, make_backend(settings, on_job_finished), metrics)
    metrics.bind(services.backend)
    services.access = Access(settings, metrics.registry)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await services.start()
        try:
            yield
        finally:
            await services.stop()

    app = FastAPI(title="Fundamental forms service", version=VERSION, description=DESCRIPTION,
                  lifespan=lifespan, openapi_tags=TAGS, separate_input_output_schemas=False,
                  docs_url=None, redoc_url=None)  # served by routes.docs, without a CDN
    app.state.services = services
    install_handlers(app)
    for router in (operations.router, jobs.router, sessions.router, health.router,
                   web.router, docs.router):
        app.include_router(router)
    app.include_router(access.router)
    app.mount("/static", web.static_files(), name="static")

    app.add_middleware(OriginMiddleware, allowed=settings.cors_origins)  # inside the metrics
    app.add_middleware(AuthMiddleware, access=services.access)  # every route, WebSockets too
    app.add_middleware(SecurityHeadersMiddleware)  # on every answer, the 403s included
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(ParallelGZipMiddleware, minimum_size=settings.gzip_minimum_size,
                       compresslevel=settings.gzip_level)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["*"], allow_headers=["*"],
                           expose_headers=["Location", "Retry-After", "Server-Timing",
                                           "RateLimit", "RateLimit-Policy",
                                           "WWW-Authenticate"])

    def custom_openapi() -> dict[str, Any]:
        return declare_bearer(openapi.build(app))

    app.openapi = custom_openapi  # type: ignore[method-assign]
    return app


app = create_app()
