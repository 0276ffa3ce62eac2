"""Security headers on every response: ``X-Content-Type-Options: nosniff``, ``X-Frame-Options:
DENY`` and a Content-Security-Policy with ``frame-ancestors 'none'``.

API responses get ``default-src 'none'`` (nothing in them may load anything). HTML pages
(the web page, ``/docs``, ``/redoc``) get a policy that allows this origin's scripts, styles,
workers, WebSockets (``'self'`` covers this origin's ``ws:``/``wss:`` since Chrome 71, Firefox
and Safari 16; a bare ``ws:`` would allow every host) and ``data:``/``blob:`` images, plus
each inline ``<script>`` of the page
by its SHA-256 hash (the page's import map, the docs' start-up script): no
``'unsafe-inline'`` scripts, and no source outside this origin (Swagger UI and ReDoc are
served from ``/static/vendor/``).

A revalidation answer (304 Not Modified) carries the same headers as the 200 it confirms:
browsers merge a 304's headers into their cached copy, so a 304 with another policy would
change the policy of a cached script (the page's worker could no longer reach the API). A
304 has no ``Content-Type``: its media type is guessed from the path, and an HTML page's
304 keeps the policy its file computes (:func:`page_policy`, set by the static files app).
"""

from __future__ import annotations

import base64
import hashlib
import mimetypes
import re

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

API_POLICY = "default-src 'none'; frame-ancestors 'none'"
WORKER_POLICY = "default-src 'self'; connect-src 'self'; frame-ancestors 'none'"
"""Scripts' policy: it governs a worker started from the script (the page's js/worker.js
fetches from this origin and imports its modules), and nothing else."""
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
            f"script-src 'self' {hashes}; "
            "style-src 'self' 'unsafe-inline'; "
            "img-src 'self' data: blob:; "
            "worker-src 'self' blob:; connect-src 'self'; "
            "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")


def response_media(status: int, headers: MutableHeaders, scope: Scope) -> str:
    """The media type an answer's policy depends on: its ``Content-Type``, or for a 304 (which
    has none) the type of the file its path names, as its 200 had."""
    media = headers.get("content-type", "")
    if media or status != 304:
        return media
    return mimetypes.guess_type(scope.get("path", ""))[0] or ""


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
                media = response_media(message["status"], headers, scope)
                if message["status"] == 304 and media.startswith("text/html"):
                    await send(message)  # the static files app set the page's policy
                elif not media.startswith("text/html"):
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
