"""Fixtures of the client tests: real uvicorn servers on loopback."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from helpers.servers import uvicorn_server


@pytest.fixture(scope="session")
def server() -> Iterator[str]:
    """Base URL of a real uvicorn with 2 workers and the default limits."""
    with uvicorn_server() as base:
        yield base


@pytest.fixture(scope="module")
def busy_server() -> Iterator[str]:
    """A real uvicorn with one worker and no queue: a second task at once is a 503."""
    with uvicorn_server({"FFS_WORKERS": "1", "FFS_QUEUE_SIZE": "0"}) as base:
        yield base
