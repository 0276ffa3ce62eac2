"""uvicorn's HTTP protocol with a deadline for the request head (slow clients, slow-loris).

uvicorn bounds the idle time between requests (``--timeout-keep-alive``) but not the time a
client takes to send a request's headers: a connection that trickles one header byte per
second stays open for ever. :class:`HeaderTimeoutProtocol` answers 408 and closes the
connection when the head of a request is not complete within FFS_HEADER_TIMEOUT seconds of
its first byte (or of the connection). The body has its own deadline (FFS_BODY_TIMEOUT,
:func:`service.http.bodies.read_body`).

Use it with ``python -m service``, or ``uvicorn service.app:app --http
service.http.server:HeaderTimeoutProtocol``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import orjson
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.settings import Settings

logger = logging.getLogger("service")

PROTOCOL = "service.http.server:HeaderTimeoutProtocol"
"""The import string to give uvicorn's ``http`` option."""


def raw_problem(status: int, reason: str, kind: str, title: str, detail: str) -> bytes:
    """A complete HTTP/1.1 response carrying a problem document, then ``close``.

    For answers given below the app (the header deadline, a request uvicorn cannot parse).

    Args:
        status: The HTTP status.
        reason: Its reason phrase.
        kind: The problem kind.
        title: The kind's title.
        detail: What happened.

    Returns:
        The response bytes.
    """
    body = orjson.dumps({"type": f"/problems/{kind}", "title": title, "status": status,
                         "detail": detail, "kind": kind, "errors": []})
    return (f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/problem+json\r\n"
            f"x-content-type-options: nosniff\r\nconnection: close\r\n"
            f"content-length: {len(body)}\r\n\r\n").encode() + body


TIMEOUT_RESPONSE = raw_problem(408, "Request Timeout", "header-timeout", "Request head too slow",
                               "the request headers did not arrive in time "
                               "(FFS_HEADER_TIMEOUT); the connection is closed")


class HeaderTimeoutProtocol(HttpToolsProtocol):
    """:class:`HttpToolsProtocol` that closes connections whose request head is too slow."""

    header_timeout: float = Settings().header_timeout
    send_timeout: float = Settings().send_timeout

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_timer: asyncio.TimerHandle | None = None
        self._send_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm(answer=False)  # nothing sent yet (a browser's preconnect): close silently

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to bytes that are not HTTP, as a problem document."""
        self.transport.write(raw_problem(400, "Bad Request", "malformed-request",
                                         "Malformed request", msg.rstrip(".")))
        self.transport.close()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._arm(answer=True)  # the first byte of a request (again on a kept-alive connection)

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()

    def pause_writing(self) -> None:
        """The client stopped reading (the write buffer is over its high-water mark): it
        has FFS_SEND_TIMEOUT s to drain it, then the connection is aborted and the buffered
        response freed (30 slow readers of an 8.7 MB answer held 300 MB)."""
        super().pause_writing()
        if self._send_timer is None:
            self._send_timer = self.loop.call_later(self.send_timeout, self._stalled)

    def resume_writing(self) -> None:
        super().resume_writing()
        if self._send_timer is not None:
            self._send_timer.cancel()
            self._send_timer = None

    def _stalled(self) -> None:
        self._send_timer = None
        if not self.transport.is_closing():
            logger.info("aborted a connection that read nothing for %g s (FFS_SEND_TIMEOUT; "
                        "%d bytes buffered)", self.send_timeout,
                        self.transport.get_write_buffer_size())
        self.transport.abort()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._send_timer is not None:
            self._send_timer.cancel()
            self._send_timer = None
        self._disarm()
        super().connection_lost(exc)

    def _arm(self, answer: bool) -> None:
        self._disarm()
        self._head_timer = self.loop.call_later(self.header_timeout, self._too_slow, answer)

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _too_slow(self, answer: bool) -> None:
        self._head_timer = None
        if self.cycle is not None and not self.cycle.response_complete:
            return  # a request is being served: its head arrived (the body has its own timeout)
        if not self.transport.is_closing():
            if answer:  # a request began: say why (an idle connection is just closed)
                self.transport.write(TIMEOUT_RESPONSE)
            self.transport.close()
