"""gzip responses: Starlette's :class:`~starlette.middleware.gzip.GZipMiddleware`, except that
a large complete body is deflated in pieces on every core at once (as pigz does).

A mesh result of 1 MB of JSON takes ~9 ms to deflate at level 1 on one core, the largest
part of what gzip adds to a synchronous solve. The pieces are independent raw deflate
streams, each primed with the 32 KiB before it (so the ratio barely changes), all but the
last ending in a sync flush (byte-aligned, not final), joined into one gzip member whose
CRC-32 and length cover the whole body: any gzip reader decodes it as one stream. Bodies
below :data:`PARALLEL_MINIMUM` and streamed responses take Starlette's own path.
"""

from __future__ import annotations

import os
import zlib
from concurrent.futures import ThreadPoolExecutor

from starlette.datastructures import Headers
from starlette.middleware.gzip import GZipMiddleware, GZipResponder
from starlette.types import Receive, Scope, Send

PARALLEL_MINIMUM = 256 * 1024
"""Complete bodies at least this large are deflated in parallel pieces."""
WINDOW = 32 * 1024
"""The deflate window: each piece is primed with this much of the data before it."""
GZIP_HEADER = b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\xff"
"""A gzip member header: deflate, no flags, no mtime, unknown OS (RFC 1952)."""

_pool: ThreadPoolExecutor | None = None


def _threads() -> int:
    return max(1, os.cpu_count() or 1)


def _piece(data: memoryview, level: int, last: bool, primer: bytes) -> bytes:
    """Raw deflate of ``data`` primed with ``primer``; a sync flush unless ``last``."""
    compressor = (zlib.compressobj(level, zlib.DEFLATED, -zlib.MAX_WBITS, zdict=primer)
                  if primer else zlib.compressobj(level, zlib.DEFLATED, -zlib.MAX_WBITS))
    return compressor.compress(data) + compressor.flush(zlib.Z_FINISH if last
                                                        else zlib.Z_SYNC_FLUSH)


def gzip_parallel(body: bytes, level: int, pieces: int | None = None) -> bytes:
    """A body gzipped in parallel.

    Args:
        body: The bytes.
        level: The zlib level.
        pieces: How many pieces deflate in parallel (default: one per core; zlib releases
            the GIL while it deflates).

    Returns:
        One gzip member of ``body``.
    """
    global _pool
    size = len(body)
    pieces = max(1, min(pieces or _threads(), size // WINDOW))
    step = max(1, -(-size // pieces))
    view = memoryview(body)
    bounds = [(start, min(start + step, size)) for start in range(0, size, step)] or [(0, 0)]
    if _pool is None:
        _pool = ThreadPoolExecutor(_threads(), thread_name_prefix="ffs-gzip")
    rest = [_pool.submit(_piece, view[a:b], level, b == size, bytes(view[max(0, a - WINDOW):a]))
            for a, b in bounds[1:]]
    first = _piece(view[:bounds[0][1]], level, len(bounds) == 1, b"")
    crc = zlib.crc32(body)
    return b"".join([GZIP_HEADER, first, *(f.result() for f in rest),
                     crc.to_bytes(4, "little"), (size & 0xFFFFFFFF).to_bytes(4, "little")])


class ParallelGZipResponder(GZipResponder):
    """Starlette's gzip responder; a complete body of at least PARALLEL_MINIMUM bytes is
    deflated by :func:`gzip_parallel` (this runs in Starlette's compression thread)."""

    def _compress_body(self, body: bytes, more_body: bool) -> bytes:
        if more_body or self._compressor is not None or len(body) < PARALLEL_MINIMUM:
            return super()._compress_body(body, more_body)
        return gzip_parallel(body, self.compresslevel)


class ParallelGZipMiddleware(GZipMiddleware):
    """:class:`GZipMiddleware` answering with :class:`ParallelGZipResponder`."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or "gzip" not in Headers(scope=scope).get(
                "Accept-Encoding", ""):
            await super().__call__(scope, receive, send)
            return
        await ParallelGZipResponder(
            self.app, self.minimum_size, compresslevel=self.compresslevel,
            thread_minimum_size=self.thread_minimum_size,
            exclude_content_types=self.exclude_content_types)(scope, receive, send)
