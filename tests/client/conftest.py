"""Fixtures of the client tests: real uvicorn servers on loopback."""

from __future__ import annotations

from tests.helpers.servers import uvicorn_fixture

server = uvicorn_fixture(doc="Base URL of a real uvicorn with 2 workers and the default limits.")
busy_server = uvicorn_fixture(
    {"FFS_WORKERS": "1", "FFS_QUEUE_SIZE": "0"}, scope="module",
    doc="A real uvicorn with one worker and no queue: a second task at once is a 503.")
