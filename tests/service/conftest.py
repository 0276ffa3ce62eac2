"""Fixtures of the service tests: the shared in-process app and the shared real uvicorn
(:mod:`tests.helpers.servers`)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.helpers.servers import TestClient, running_app, uvicorn_fixture


@pytest.fixture(scope="session")
def client() -> Iterator[TestClient]:
    """The shared in-process app (2 workers, default limits)."""
    with running_app() as c:
        yield c


live_server = uvicorn_fixture(
    doc="Base URL of a real uvicorn server shared by the end-to-end tests.")
