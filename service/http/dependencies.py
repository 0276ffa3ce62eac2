"""The routes' collaborators as typed FastAPI dependencies.

``create_app`` stores one :class:`Services` on ``app.state.services``; a route declares what
it needs (``settings: SettingsDep``, ``jobs: JobsDep``, ...) instead of reaching into
``request.app.state``. The dependencies take an ``HTTPConnection``, so WebSocket routes use
them too.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends
from starlette.requests import HTTPConnection

from service.backends.contracts import Backend, Executor, JobService, SessionBackend
from service.http.auth import Access, caller
from service.http.bodies import ParserPool
from service.http.metrics import ServiceMetrics
from service.settings import Settings


@dataclass
class Services:
    """Everything the routes use, started and stopped together by the app's lifespan.

    Attributes:
        settings: The service's settings.
        backend: The compute backend (workers, jobs, sessions).
        metrics: The Prometheus metrics.
        parser: The process that validates the largest bodies (:mod:`service.http.bodies`).
        started: True between :meth:`start` and :meth:`stop`.
    """

    settings: Settings
    backend: Backend
    metrics: ServiceMetrics = field(default_factory=ServiceMetrics)
    parser: ParserPool = field(default_factory=ParserPool)
    started: bool = False
    access: Access | None = None
    """The API keys and their quotas (:mod:`service.http.auth`); None: keys off."""

    async def start(self) -> None:
        """Start the backend, then open the parser."""
        await self.backend.start()
        self.parser.start()
        self.started = True

    def settings_for(self, connection: HTTPConnection) -> Settings:
        """The settings of one request: its key's face quota as FFS_MAX_FACES where lower
        (:meth:`service.http.auth.Access.effective_settings`)."""
        if self.access is None:
            return self.settings
        return self.access.effective_settings(self.settings, caller(connection))

    async def stop(self) -> None:
        """Stop the backend (its workers, jobs and sessions), then end the parser process."""
        self.started = False
        try:
            if self.access is not None:
                await self.access.stop()
            await self.backend.stop()
        finally:
            await asyncio.to_thread(self.parser.stop)


def services(connection: HTTPConnection) -> Services:
    """The app's :class:`Services` (the other dependencies read one member of it).

    Args:
        connection: The request or WebSocket.

    Returns:
        ``app.state.services``.
    """
    found: Services = connection.app.state.services
    return found


def settings(connection: HTTPConnection) -> Settings:
    """The settings, with the caller's key's face quota as FFS_MAX_FACES where lower."""
    return services(connection).settings_for(connection)


def executor(connection: HTTPConnection) -> Executor:
    return services(connection).backend.executor


def jobs(connection: HTTPConnection) -> JobService:
    return services(connection).backend.jobs


def sessions(connection: HTTPConnection) -> SessionBackend:
    return services(connection).backend.sessions


def metrics(connection: HTTPConnection) -> ServiceMetrics:
    return services(connection).metrics


def parser(connection: HTTPConnection) -> ParserPool:
    return services(connection).parser


ServicesDep = Annotated[Services, Depends(services)]
SettingsDep = Annotated[Settings, Depends(settings)]
ExecutorDep = Annotated[Executor, Depends(executor)]
JobsDep = Annotated[JobService, Depends(jobs)]
SessionsDep = Annotated[SessionBackend, Depends(sessions)]
MetricsDep = Annotated[ServiceMetrics, Depends(metrics)]
ParserDep = Annotated[ParserPool, Depends(parser)]
