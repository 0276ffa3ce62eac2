"""Who is calling: API keys at the HTTP edge (off unless FFS_API_KEYS or FFS_API_KEYS_FILE
gives keys; docs/deployment.md#api-keys).

:class:`AuthMiddleware` runs on every request and WebSocket handshake of the app, so any
route, also one added later, is covered: the public paths (:data:`PUBLIC_PATHS`: health
checks, the page, its files, the API documentation and the problem catalogue) pass; every
other one needs ``Authorization: Bearer <key>`` (a WebSocket may instead offer the
subprotocols ``ffs`` and ``bearer.<key>``, since browsers cannot set headers on one; the
key never goes into a URL, which access logs would keep). A missing or unknown key is
answered 401 ``unauthorized`` with ``WWW-Authenticate: Bearer``; a key without the role a
path needs (:data:`ADMIN_PATHS`) 403 ``forbidden``; a key past its requests per minute 429
``rate-limited`` with ``Retry-After``, ``RateLimit`` and ``RateLimit-Policy`` (every
authenticated answer carries the last two). The request is not executed in any of these
cases.

The caller (:class:`Caller`) is left in the request's state for the routes
(:data:`CallerDep`): it owns the jobs and sessions it creates (:attr:`Caller.owner`;
another key is answered 404 for them, an admin key sees all), and carries its quotas. With
keys off, the caller is its address, as the per-address limits always counted.
Key material never reaches a log, a problem document or a metric: only key *names* do.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends
from prometheus_client import CollectorRegistry, Counter
from starlette.datastructures import Headers, MutableHeaders
from starlette.requests import HTTPConnection
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.access.keys import ApiKey, KeyLimits, KeyRing, ring_from_file, ring_from_mapping
from service.access.quotas import Quota, RateLimiter
from service.access.webhooks import WebhookPolicy, WebhookSender
from service.api.problems import ProblemError, element_error
from service.http.problems import problem_response
from service.settings import Settings

PUBLIC_PATHS = ("/healthz", "/readyz", "/", "/favicon.ico", "/openapi.json", "/docs",
                "/redoc")
"""Paths served without a key (exactly)."""
PUBLIC_PREFIXES = ("/static/", "/problems", "/docs/", "/redoc/")
"""Path prefixes served without a key."""
ADMIN_PATHS = ("/metrics",)
"""Paths only an ``admin`` key may use."""
WS_SUBPROTOCOL = "ffs"
"""The subprotocol a WebSocket is accepted with when the client offered it."""
WS_BEARER_PREFIX = "bearer."
"""A WebSocket subprotocol ``bearer.<key>`` carries the key (never echoed back)."""
REALM = "ffs"
CALLER_STATE = "ffs_caller"


@dataclass(frozen=True)
class Caller:
    """Who sent a request: a key (keys on) or only an address (keys off)."""

    key: ApiKey | None
    address: str | None

    @property
    def name(self) -> str | None:
        """The key's name (None without keys)."""
        return self.key.name if self.key else None

    @property
    def is_admin(self) -> bool:
        return self.key is not None and self.key.is_admin

    @property
    def owner(self) -> str | None:
        """What its jobs and sessions record as their owner: ``key:<name>``, or the
        address without keys (for the per-address limits)."""
        return f"key:{self.key.name}" if self.key else self.address

    def sees(self, owner: str | None) -> bool:
        """Whether this caller may see a job or session of ``owner`` (keys off: anyone)."""
        return self.key is None or self.key.is_admin or owner == self.owner

    @property
    def concurrent_jobs(self) -> int | None:
        """Its quota of unfinished jobs (None: the per-address FFS_MAX_CLIENT_JOBS)."""
        return self.key.limits.concurrent_jobs if self.key else None

    @property
    def concurrent_sessions(self) -> int | None:
        """Its quota of open sessions (None: FFS_MAX_CLIENT_SESSIONS)."""
        return self.key.limits.concurrent_sessions if self.key else None


def default_limits(settings: Settings) -> KeyLimits:
    """The limits of a key that sets none (FFS_KEY_*)."""
    return KeyLimits(settings.key_requests_per_minute, settings.key_concurrent_jobs,
                     settings.key_concurrent_sessions,
                     settings.key_max_faces or settings.max_faces)


def key_ring(settings: Settings) -> KeyRing:
    """The keys of FFS_API_KEYS and FFS_API_KEYS_FILE (none: keys are off)."""
    defaults = default_limits(settings)
    plain = settings.api_key_mapping()
    in_file = set()
    keys = []
    if settings.api_keys_file is not None:
        keys = ring_from_file(settings.api_keys_file, defaults, settings.admin_keys)
        in_file = {k.name for k in keys}
    admins = [n for n in settings.admin_keys if n not in in_file or n in plain]
    keys += ring_from_mapping(plain, admins, defaults)
    return KeyRing(keys, required=settings.api_keys_file is not None)


class KeyMetrics:
    """Per-key counters, labelled by key *name* only."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.requests = Counter("ffs_key_requests", "Authenticated requests by key name.",
                                ["key"], registry=registry)
        self.throttled = Counter("ffs_key_throttled",
                                 "Requests refused by a key's quota (429), by key name and "
                                 "quota.", ["key", "quota"], registry=registry)
        self.refused = Counter("ffs_auth_refused",
                               "Requests refused for a missing or unknown key (401) or a role "
                               "(403).", ["reason"], registry=registry)
        self.webhooks = Counter("ffs_webhook_deliveries",
                                "Webhook deliveries: delivered, retried (an attempt failed) "
                                "or given-up.", ["outcome"], registry=registry)


class Access:
    """The keys, their request counters and their metrics, for one app."""

    def __init__(self, settings: Settings, registry: CollectorRegistry) -> None:
        self.settings = settings
        self.ring = key_ring(settings)
        self.limiter = RateLimiter()
        self.metrics = KeyMetrics(registry)
        self.webhooks = WebhookSender(
            WebhookPolicy(tuple(settings.webhook_hosts), settings.webhook_attempts,
                          settings.webhook_backoff, settings.webhook_timeout),
            lambda outcome: self.metrics.webhooks.labels(outcome).inc())

    async def stop(self) -> None:
        """Stop following jobs for their webhooks (unsent ones are dropped)."""
        await self.webhooks.stop()

    @property
    def enabled(self) -> bool:
        return self.ring.enabled

    def effective_settings(self, settings: Settings, caller: Caller) -> Settings:
        """``settings`` with the caller's face quota as FFS_MAX_FACES, where it is lower."""
        if caller.key is None or caller.key.limits.max_faces is None:
            return settings
        faces = min(settings.max_faces, caller.key.limits.max_faces)
        if faces == settings.max_faces:
            return settings
        return settings.model_copy(update={"max_faces": faces})


def is_public(path: str) -> bool:
    return path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)


def presented_key(scope: Scope) -> str | None:
    """The key a request presents: the Bearer token of ``Authorization``, or (WebSocket
    only) the ``bearer.<key>`` subprotocol."""
    headers = Headers(scope=scope)
    scheme, _, token = headers.get("authorization", "").strip().partition(" ")
    if scheme.lower() == "bearer" and token.strip():
        return token.strip()
    if scope["type"] == "websocket":
        for offered in scope.get("subprotocols", ()):
            if offered.startswith(WS_BEARER_PREFIX) and len(offered) > len(WS_BEARER_PREFIX):
                return offered[len(WS_BEARER_PREFIX):]
    return None


def accepted_subprotocol(scope: Scope) -> str | None:
    """The subprotocol to accept a WebSocket with: ``ffs`` when offered (a browser that
    offers subprotocols fails a handshake that selects none), else none."""
    return WS_SUBPROTOCOL if WS_SUBPROTOCOL in scope.get("subprotocols", ()) else None


def _unauthorized(presented: str | None) -> ProblemError:
    challenge = f'Bearer realm="{REALM}"'
    if presented is None:
        detail = ("this service requires an API key: send Authorization: Bearer <key> (a "
                  "WebSocket may offer the subprotocols ffs and bearer.<key>)")
    else:
        detail = "the API key is not known to this service (it may have been revoked)"
        challenge += ', error="invalid_token"'
    return ProblemError("unauthorized", detail, headers={"WWW-Authenticate": challenge},
                        errors=[element_error("Authorization", "missing" if presented is None
                                              else "unknown key")])


def _forbidden(caller: Caller, path: str) -> ProblemError:
    role = caller.key.role if caller.key else "none"
    return ProblemError("forbidden", f"the key {caller.name!r} (role {role}) may not use "
                        f"{path}: it needs the admin role",
                        errors=[element_error("Authorization", "needs the admin role")])


class AuthMiddleware:
    """Pure ASGI middleware: authenticates, authorizes and rate-limits (module docstring)."""

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        client = scope.get("client")
        address = client[0] if client else None
        state = scope.setdefault("state", {})
        path = scope.get("path", "")
        if not self.access.enabled or is_public(path):
            state[CALLER_STATE] = Caller(None, address)
            await self.app(scope, receive, send)
            return
        presented = presented_key(scope)
        key = self.access.ring.authenticate(presented)
        if key is None:
            self.access.metrics.refused.labels("unauthorized").inc()
            await _refuse(scope, receive, send, _unauthorized(presented))
            return
        caller = Caller(key, address)
        state[CALLER_STATE] = caller
        if path in ADMIN_PATHS and not caller.is_admin:
            self.access.metrics.refused.labels("forbidden").inc()
            await _refuse(scope, receive, send, _forbidden(caller, path))
            return
        decision = self.access.limiter.take(key.name, key.limits.requests_per_minute or 1)
        if not decision.allowed:
            self.access.metrics.throttled.labels(key.name, "requests").inc()
            await _refuse(scope, receive, send, ProblemError(
                "rate-limited", f"the key {key.name!r} made its {decision.limit} requests of "
                f"this minute; retry in {decision.retry_after} s",
                headers=decision.headers(), limit=decision.limit,
                retry_after=decision.retry_after))
            return
        self.access.metrics.requests.labels(key.name).inc()
        await self.app(scope, receive, self._answering(send, key.name, decision.headers()))

    def _answering(self, send: Send, name: str, headers: dict[str, str]
                   ) -> Callable[[Message], Awaitable[None]]:
        """``send`` adding the request-rate headers, and counting a route's 429 of a
        concurrent quota (named by its RateLimit-Policy) in ``ffs_key_throttled_total``."""
        async def sender(message: Message) -> None:
            if message["type"] == "http.response.start":
                mutable = MutableHeaders(scope=message)
                if message["status"] == 429 and "ratelimit-policy" in mutable:
                    quota = mutable["ratelimit-policy"].split(";", 1)[0].strip('"')
                    self.access.metrics.throttled.labels(name, quota).inc()
                for header, value in headers.items():
                    if header not in mutable:
                        mutable[header] = value
            await send(message)
        return sender


DRAIN_BYTES = 1024 * 1024
"""A refused request's body is read up to this many bytes before the answer, so that a
client still sending a small upload reads the 401 instead of a reset connection (a larger
one is cut: its connection closes)."""
DRAIN_SECONDS = 2.0


async def _drain(receive: Receive) -> None:
    """Read what is left of a small request body (at most :data:`DRAIN_BYTES`, for at most
    :data:`DRAIN_SECONDS`)."""
    async def read() -> None:
        received = 0
        while received <= DRAIN_BYTES:
            message = await receive()
            if message["type"] != "http.request":
                return
            received += len(message.get("body", b""))
            if not message.get("more_body", False):
                return
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(read(), DRAIN_SECONDS)


async def _refuse(scope: Scope, receive: Receive, send: Send, problem: ProblemError) -> None:
    """Answer ``problem``; a WebSocket handshake is refused with it (an HTTP answer)."""
    response = problem_response(problem, scope.get("path"))
    if scope["type"] == "websocket":
        headers = [(k.encode("latin-1"), v.encode("latin-1"))
                   for k, v in response.headers.items() if k.lower() != "content-length"]
        await send({"type": "websocket.http.response.start", "status": problem.status,
                    "headers": headers})
        await send({"type": "websocket.http.response.body", "body": response.body})
        return
    await _drain(receive)
    await response(scope, receive, send)


def caller(connection: HTTPConnection) -> Caller:
    """The request's :class:`Caller` (set by :class:`AuthMiddleware`)."""
    found = connection.scope.get("state", {}).get(CALLER_STATE)
    if found is None:
        client = connection.client
        return Caller(None, client.host if client else None)
    assert isinstance(found, Caller)
    return found


CallerDep = Annotated[Caller, Depends(caller)]


def quota_problem(caller: Caller, quota: Quota, limit: int, what: str) -> ProblemError:
    """The 429 of a key at its concurrent ``quota`` (jobs or sessions)."""
    return ProblemError(
        "quota-exceeded", f"the key {caller.name!r} already has {limit} {what} (its quota "
        f"{quota.name}); wait for one to finish or close one",
        headers={"Retry-After": "5", **quota.headers(limit, 0, 5)}, quota=quota.name,
        limit=limit)


def declare_bearer(document: dict[str, Any]) -> dict[str, Any]:
    """Declare the optional bearer scheme in an OpenAPI document: Swagger UI's Authorize
    button then sends the key; every operation outside the public paths documents 401,
    403 and 429."""
    schemes = document.setdefault("components", {}).setdefault("securitySchemes", {})
    schemes["bearerAuth"] = {
        "type": "http", "scheme": "bearer",
        "description": "An API key (only when the service has keys: FFS_API_KEYS or "
                       "FFS_API_KEYS_FILE); without keys no header is needed."}
    problem = {"application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}}
    extra = {"401": "No API key, or an unknown one (services with keys).",
             "403": "The key's role does not allow this.",
             "429": "The key's quota is used up; retry after Retry-After seconds."}
    for path, item in document.get("paths", {}).items():
        for operation in item.values():
            if not isinstance(operation, dict) or "responses" not in operation:
                continue
            if is_public(path):
                operation["security"] = []
                continue
            operation["security"] = [{"bearerAuth": []}, {}]
            for code, description in extra.items():
                operation["responses"].setdefault(code, {"description": description,
                                                         "content": problem})
    return document
