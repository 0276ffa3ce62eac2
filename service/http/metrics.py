"""Prometheus metrics: HTTP requests and latencies per route, solver stage timings, queue depth,
pool size. Each app has its own registry (several apps can live in one test process).
"""

from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.task import TaskResult
from service.backends.contracts import Backend

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0,
                   120.0)
SOLVE_BUCKETS = (0.005, 0.01, 0.02, 0.03, 0.04, 0.05, 0.075, 0.1, 0.25, 0.5, 1.0, 5.0)
METRICS_CONTENT_TYPE = CONTENT_TYPE_LATEST


class ServiceMetrics:
    """The service's collectors in one registry."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.requests = Counter("ffs_http_requests", "HTTP requests by route and status.",
                                ["method", "route", "status"], registry=r)
        self.latency = Histogram("ffs_http_request_duration_seconds",
                                 "HTTP request latency by route.", ["method", "route"],
                                 buckets=LATENCY_BUCKETS, registry=r)
        self.stage = Histogram("ffs_solver_stage_duration_seconds",
                               "Time per solver stage in the workers.", ["operation", "stage"],
                               buckets=LATENCY_BUCKETS, registry=r)
        self.tasks = Counter("ffs_tasks", "Finished solver tasks by operation and outcome.",
                             ["operation", "outcome"], registry=r)
        self.queue_depth = Gauge("ffs_queue_depth", "Tasks waiting for a worker.", registry=r)
        self.pool_size = Gauge("ffs_pool_size", "Configured worker processes.", registry=r)
        self.pool_ready = Gauge("ffs_pool_ready_workers", "Worker processes ready.", registry=r)
        self.pool_busy = Gauge("ffs_pool_busy_workers", "Workers running a task.", registry=r)
        self.worker_restarts = Gauge("ffs_worker_restarts",
                                     "Worker processes replaced (crash, cancel, timeout).",
                                     registry=r)
        self.jobs = Gauge("ffs_jobs", "Stored jobs by status.", ["status"], registry=r)
        self.sessions = Gauge("ffs_sessions", "Open deformation sessions.", registry=r)
        self.session_memory = Gauge("ffs_session_memory_bytes",
                                    "Memory held by open sessions.", registry=r)
        self.sessions_created = Counter("ffs_sessions_created", "Sessions opened.",
                                        registry=r)
        self.session_solves = Histogram("ffs_session_solve_duration_seconds",
                                        "Session solves (one drag) by transport.",
                                        ["transport"], buckets=SOLVE_BUCKETS, registry=r)
        self.session_drops = Counter("ffs_session_dropped_drags",
                                     "WebSocket drags replaced by a newer one before they "
                                     "were solved.", registry=r)

    def bind(self, backend: Backend) -> None:
        """Read the pool, job and session gauges from a backend at scrape time.

    Args:
        backend: The app's backend.
    """
        executor = backend.executor
        self.queue_depth.set_function(executor.queue_depth)
        self.pool_size.set_function(executor.size)
        self.pool_ready.set_function(executor.workers_ready)
        self.pool_busy.set_function(executor.busy)
        self.worker_restarts.set_function(lambda: executor.restarts)
        self._job_counts = backend.jobs.counts
        self.sessions.set_function(backend.sessions.count)
        self.session_memory.set_function(backend.sessions.memory)

    def session_created(self) -> None:
        """Count a session opened."""
        self.sessions_created.inc()

    def session_solve(self, transport: str, seconds: float) -> None:
        """Record a drag's solve.

        Args:
            transport: ``http`` or ``ws``.
            seconds: Its time.
        """
        self.session_solves.labels(transport).observe(seconds)

    def session_dropped(self) -> None:
        """Count a WebSocket drag replaced by a newer one before it was solved."""
        self.session_drops.inc()

    def observe_task(self, operation: str, result: TaskResult | None, outcome: str) -> None:
        """Count a finished task and record its stage timings.

        Args:
            operation: The task's operation.
            result: Its result (its ``timings``), or None when it failed.
            outcome: ``ok``, ``rejected``, ``timeout``, ``disconnected``, ``error`` (a
                client's) or ``failed``.
        """
        self.tasks.labels(operation, outcome).inc()
        for stage, seconds in (result.timings if result is not None else {}).items():
            self.stage.labels(operation, stage).observe(seconds)

    def render(self) -> bytes:
        """The Prometheus exposition of every metric (job counts read now)."""
        counts = getattr(self, "_job_counts", None)
        if counts is not None:
            for status, count in counts().items():
                self.jobs.labels(status).set(count)
        return generate_latest(self.registry)


class MetricsMiddleware:
    """Pure ASGI middleware: count requests and time them by route template."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            name = getattr(route, "path", None) or "unmatched"
            method = scope.get("method", "")
            self.metrics.requests.labels(method, name, str(status)).inc()
            self.metrics.latency.labels(method, name).observe(time.perf_counter() - start)
