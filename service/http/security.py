"""Security headers on every response: ``X-Content-Type-Options: nosniff``, ``X-Frame-Options:
DENY`` and a Content-Security-Policy with ``frame-ancestors 'none'``.

API responses get ``default-src 'none'`` (nothing in them may load anything). HTML pages
(the web page, ``/docs``, ``/redoc``) get a policy that allows this origin's scripts, styles,
workers, WebSockets and ``data:``/``blob:`` images, plus each inline ``<script>`` of the page
by its SHA-256 hash (the page's import map, the docs' start-up script): no
``'unsafe-inline'`` scripts. :data:`DOCS_SOURCES` lists what the docs pages load from
elsewhere while they load Swagger UI and ReDoc from a CDN.
"""

from __future__ import annotations

import base64
import hashlib
import re

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

API_POLICY = "default-src 'none'; frame-ancestors 'none'"
WORKER_POLICY = "default-src 'self'; connect-src 'self'; frame-ancestors 'none'"
"""Scripts' policy: it governs a worker started from the script (the page's js/worker.js
fetches from this origin and imports its modules), and nothing else."""
DOCS_SOURCES = "https://cdn.jsdelivr.net"
"""Where FastAPI's /docs and /redoc pages load their scripts and styles from (until they are
served locally)."""
_INLINE_SCRIPT = re.compile(rb"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.S | re.I)


def page_policy(html: bytes) -> str:
    """The Content-Security-Policy of an HTML page.

    Args:
        html: The page.

    Returns:
        The policy: this origin, and the page's inline scripts by hash.
    """
    hashes = " ".join(
        "'sha256-" + base64.b64encode(hashlib.sha256(body).digest()).decode() + "'"
        for body in _INLINE_SCRIPT.findall(html))
    return ("default-src 'self'; "
            f"script-src 'self' {hashes} {DOCS_SOURCES}; "
            f"style-src 'self' 'unsafe-inline' {DOCS_SOURCES}; "
            "img-src 'self' data: blob: https://fastapi.tiangolo.com; "
            "worker-src 'self' blob:; connect-src 'self' ws: wss:; "
            "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")


class SecurityHeadersMiddleware:
    """Pure ASGI middleware adding the headers of the module docstring."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start: Message | None = None
        chunks: list[bytes] = []

        async def send_with_headers(message: Message) -> None:
            nonlocal start
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers["X-Content-Type-Options"] = "nosniff"
                headers["X-Frame-Options"] = "DENY"
                media = headers.get("content-type", "")
                if not media.startswith("text/html"):
                    headers["Content-Security-Policy"] = (
                        WORKER_POLICY if "javascript" in media else API_POLICY)
                    await send(message)
                else:
                    start = message  # the policy needs the page's inline scripts
                return
            if start is None or message["type"] != "http.response.body":
                await send(message)
                return
            chunks.append(message.get("body", b""))
            if message.get("more_body", False):
                return
            html = b"".join(chunks)
            MutableHeaders(scope=start)["Content-Security-Policy"] = page_policy(html)
            await send(start)
            await send({"type": "http.response.body", "body": html})

        await self.app(scope, receive, send_with_headers)
