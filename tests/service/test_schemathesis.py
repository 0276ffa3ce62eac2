"""Schemathesis against a real uvicorn: every operation of openapi/openapi.json with generated
inputs, then stateful runs that follow the document's links (session create -> solve, state,
delete; job submit -> status, result, cancel). Any 5xx, or a response whose status, content
type, headers or body the document does not describe, fails the test.

Bounded: a fixed number of examples per operation and of stateful steps (about a minute on
a contended 2-core machine).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import httpx
import pytest
import schemathesis
from helpers.servers import uvicorn_server
from helpers.service import metric_value
from hypothesis import HealthCheck, settings
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from schemathesis.specs.openapi.checks import use_after_free

from service.api.decoding import BINARY_MEDIA_TYPE


@schemathesis.serializer(BINARY_MEDIA_TYPE)
def _raw_bytes(ctx, value) -> bytes:
    """Generated binary bodies go out as they are (mostly framing errors: 400 expected)."""
    return value if isinstance(value, bytes) else str(value).encode()


CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_headers_conformance, response_schema_conformance]
EXAMPLES = int(os.environ.get("FFS_FUZZ_EXAMPLES", "20"))
"""Examples per operation (a deeper run: FFS_FUZZ_EXAMPLES=500)."""
SETTINGS = settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
                    suppress_health_check=list(HealthCheck), database=None)
SKIP = ("/metrics",)  # text/plain Prometheus exposition: no schema to check


@pytest.fixture(scope="module")
def fuzz_server() -> Iterator[str]:
    # Small limits keep generated meshes cheap; a short request timeout bounds solves.
    # Sessions expire after 3 s, so that each test starts with none open.
    with uvicorn_server({"FFS_MAX_SESSIONS": "4", "FFS_SESSION_TTL": "3",
                         "FFS_REQUEST_TIMEOUT": "20", "FFS_QUEUE_SIZE": "64"}) as base:
        yield base


@pytest.fixture(scope="module")
def api_schema(fuzz_server: str):
    schema = schemathesis.openapi.from_url(f"{fuzz_server}/openapi.json")
    schema.config.update(base_url=fuzz_server)
    return schema


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.exclude(path=SKIP[0]).parametrize()
@SETTINGS
def test_every_operation_matches_the_document(case):
    case.call_and_validate(checks=CHECKS, timeout=60)


def _no_sessions(base: str) -> None:
    deadline = time.monotonic() + 30
    while metric_value(httpx.get(f"{base}/metrics").text, "ffs_sessions") > 0:
        assert time.monotonic() < deadline, "sessions did not expire"
        time.sleep(0.2)


def test_stateful_links(api_schema, fuzz_server):
    _no_sessions(fuzz_server)
    machine = api_schema.as_state_machine()

    class Checked(machine):  # type: ignore[misc, valid-type]
        def validate_response(self, response, case, **kwargs):
            case.validate_response(response, checks=[*CHECKS, use_after_free])

    Checked.run(settings=settings(max_examples=15, stateful_step_count=6, deadline=None,
                                  derandomize=True,
                                  suppress_health_check=list(HealthCheck), database=None))
    # The links were followed: sessions were created, solved and deleted through them.
    metrics = httpx.get(f"{fuzz_server}/metrics").text
    assert metric_value(metrics, "ffs_sessions_created_total") >= 1
    solved = {status: metric_value(metrics, "ffs_http_requests_total", status=status,
                                   route="/v1/sessions/{session_id}/solve")
              for status in ("200", "400", "404", "422")}
    assert sum(solved.values()) >= 1, solved
    assert metric_value(metrics, "ffs_http_requests_total", status="204",
                        route="/v1/sessions/{session_id}") >= 1
