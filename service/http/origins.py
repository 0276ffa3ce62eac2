"""The ``Origin`` check: a browser request from another site is refused before it does
anything.

A multipart ``POST`` needs no CORS preflight, so without this check any web page a user
visits could submit jobs or open sessions in their name (CORS only hides the answer from
that page; the work is done). A request that carries ``Origin`` (browsers send it on every
cross-origin request, every ``POST`` and every WebSocket handshake) is served only when the
origin is the service's own (its host and port are the request's ``Host``) or listed in
``FFS_CORS_ORIGINS`` (``*`` allows any); otherwise it is answered 403 ``forbidden-origin``
(a WebSocket handshake is closed with 403). Requests without ``Origin`` (curl, scripts,
same-origin ``GET`` navigations) pass.
"""

from __future__ import annotations

from collections.abc import Sequence
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.problems import ProblemError, element_error
from service.http.problems import problem_response

DEFAULT_PORTS = {"http": 80, "https": 443, "ws": 80, "wss": 443}


def _host_port(netloc: str, scheme: str) -> tuple[str, int | None]:
    parts = urlsplit(f"//{netloc}")
    try:
        port = parts.port
    except ValueError:
        return netloc.lower(), None
    return (parts.hostname or "").lower(), port or DEFAULT_PORTS.get(scheme)


def is_own_origin(origin: str, host: str | None, scheme: str) -> bool:
    """Whether an Origin names the host the request was sent to.

    Args:
        origin: The Origin header (``https://a.example:8443``).
        host: The Host header.
        scheme: The request's scheme (an origin's may differ behind a TLS proxy).

    Returns:
        True when the origin's host and port (its scheme's default port when it names
        none) are the Host header's.
    """
    if not host:
        return False
    parts = urlsplit(origin)
    if not parts.scheme or not parts.netloc:
        return False
    want = _host_port(host, "https" if parts.scheme == "https" else scheme)
    return _host_port(parts.netloc, parts.scheme) == want


class OriginMiddleware:
    """Pure ASGI middleware: 403 for a request whose ``Origin`` is neither this service's
    nor one of ``allowed`` (see the module docstring)."""

    def __init__(self, app: ASGIApp, allowed: Sequence[str]) -> None:
        self.app = app
        self.any = "*" in allowed
        self.allowed = {o.rstrip("/").lower() for o in allowed}

    def allows(self, scope: Scope) -> bool:
        headers = Headers(scope=scope)
        origin = headers.get("origin")
        if origin is None or self.any:
            return True
        origin = origin.strip().rstrip("/").lower()
        return origin in self.allowed or is_own_origin(origin, headers.get("host"),
                                                       scope.get("scheme", "http"))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or self.allows(scope):
            await self.app(scope, receive, send)
            return
        origin = Headers(scope=scope).get("origin", "")
        problem = ProblemError(
            "forbidden-origin", f"requests from the web origin {origin!r} are not allowed; "
            "the service accepts its own origin and those in FFS_CORS_ORIGINS",
            errors=[element_error("Origin", "not an allowed origin")])
        if scope["type"] == "websocket":
            await send({"type": "websocket.http.response.start", "status": 403,
                        "headers": [(b"content-type", b"application/problem+json")]})
            await send({"type": "websocket.http.response.body",
                        "body": problem_response(problem, scope.get("path")).body})
            return
        await problem_response(problem, scope.get("path"))(scope, receive, send)
