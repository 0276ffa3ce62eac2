"""The routes' collaborators as typed FastAPI dependencies.

``create_app`` stores one :class:`Services` on ``app.state.services``; a route declares what
it needs (``settings: SettingsDep``, ``jobs: JobsDep``, ...) instead of reaching into
``request.app.state``. The dependencies take an ``HTTPConnection``, so WebSocket routes use
them too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends
from starlette.requests import HTTPConnection

from service.backends.contracts import Backend, Executor, JobService, SessionBackend
from service.http.metrics import ServiceMetrics
from service.settings import Settings


@dataclass
class Services:
    """Everything the routes use: the settings, the backend, the metrics; ``started`` is
    True between the lifespan's start and stop."""

    settings: Settings
    backend: Backend
    metrics: ServiceMetrics = field(default_factory=ServiceMetrics)
    started: bool = False


def services(connection: HTTPConnection) -> Services:
    found: Services = connection.app.state.services
    return found


def settings(connection: HTTPConnection) -> Settings:
    return services(connection).settings


def executor(connection: HTTPConnection) -> Executor:
    return services(connection).backend.executor


def jobs(connection: HTTPConnection) -> JobService:
    return services(connection).backend.jobs


def sessions(connection: HTTPConnection) -> SessionBackend:
    return services(connection).backend.sessions


def metrics(connection: HTTPConnection) -> ServiceMetrics:
    return services(connection).metrics


ServicesDep = Annotated[Services, Depends(services)]
SettingsDep = Annotated[Settings, Depends(settings)]
ExecutorDep = Annotated[Executor, Depends(executor)]
JobsDep = Annotated[JobService, Depends(jobs)]
SessionsDep = Annotated[SessionBackend, Depends(sessions)]
MetricsDep = Annotated[ServiceMetrics, Depends(metrics)]
