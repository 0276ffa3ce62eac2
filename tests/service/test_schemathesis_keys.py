"""Schemathesis against a real uvicorn with API keys (issue 46): every operation with
generated inputs and the stateful link-following runs of test_schemathesis.py, each request
with an admin key (``Authorization: Bearer``); and every operation without a key, answered
with the documented 401 problem (nothing else, nothing executed).

Phases: the document's examples and hypothesis's fuzzing (:data:`KEYED_PHASES`), not
schemathesis's coverage phase. That phase sends ~7,900 boundary and negative bodies (1,400
for ``POST /v1/reconstruct/vjp`` alone): they test how each body is decoded and answered,
which test_schemathesis.py checks on a server with the same limits. A key only changes the
authorization decision, made by the ASGI middleware (service/http/auth.py) on the request's
headers before its body is read, so what the runs here check (every operation accepts the
key and still answers as documented; without it, every non-public operation answers 401) is
fuzzed on every operation without it. With it the two runs took 97 s of a whole-suite run
(144 s + 61 s on a loaded machine), without it 15 s (12 s + 3 s, same machine)."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterator

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, settings

from tests.helpers.servers import uvicorn_server
from tests.helpers.service import metric_value
from tests.service.test_schemathesis import (
    CHECKS,
    SETTINGS,
    SKIP,
    binary_as_json_body,
    run_stateful,
    steps_starting,
)

KEY = "schemathesis-key-0123456789"
AUTH = {"Authorization": f"Bearer {KEY}"}
STEPS: Counter[str] = Counter()
ANONYMOUS: Counter[int] = Counter()
KEYED_PHASES = ["examples", "fuzzing", "stateful"]
"""Schemathesis phases of the runs here (the module's docstring says why not ``coverage``)."""


@pytest.fixture(scope="module")
def keyed_fuzz_server() -> Iterator[str]:
    # As test_schemathesis.py's server, with an admin key whose quotas the run cannot reach.
    with uvicorn_server({"FFS_MAX_SESSIONS": "4", "FFS_SESSION_TTL": "3",
                         "FFS_REQUEST_TIMEOUT": "20", "FFS_QUEUE_SIZE": "64",
                         "FFS_API_KEYS": json.dumps({"fuzz": KEY}), "FFS_ADMIN_KEYS": "fuzz",
                         "FFS_KEY_REQUESTS_PER_MINUTE": "1000000",
                         "FFS_KEY_CONCURRENT_JOBS": "256",
                         "FFS_KEY_CONCURRENT_SESSIONS": "4"}) as base:
        yield base


def _schema(base: str, headers: dict[str, str]):
    doc = httpx.get(f"{base}/openapi.json", timeout=30).json()
    found = schemathesis.openapi.from_dict(binary_as_json_body(doc))
    found.config.update(base_url=base, headers=headers)
    found.config.phases.update(phases=KEYED_PHASES)
    return found


@pytest.fixture(scope="module")
def keyed_schema(keyed_fuzz_server: str):
    return _schema(keyed_fuzz_server, AUTH)


@pytest.fixture(scope="module")
def anonymous_schema(keyed_fuzz_server: str):
    return _schema(keyed_fuzz_server, {})


keyed = schemathesis.pytest.from_fixture("keyed_schema")
anonymous = schemathesis.pytest.from_fixture("anonymous_schema")


@keyed.exclude(path=SKIP[0]).parametrize()
@SETTINGS
def test_every_operation_with_a_key(case):
    response = case.call_and_validate(checks=CHECKS, timeout=60)
    # A 401 or 403 is documented, so the checks alone would pass a run without the key.
    assert response.status_code not in (401, 403), (case.operation.path, response.text)


@anonymous.exclude(path=SKIP[0]).parametrize()
@settings(max_examples=3, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck), database=None)
def test_every_operation_without_a_key(case):
    response = case.call_and_validate(checks=CHECKS, timeout=60)
    ANONYMOUS[response.status_code] += 1
    public = case.operation.path in ("/healthz", "/readyz", "/problems", "/problems/{kind}",
                                     "/", "/favicon.ico", "/docs", "/redoc", "/openapi.json")
    if not public:
        assert response.status_code == 401, (case.operation.path, response.text)


def test_nothing_ran_without_a_key(keyed_fuzz_server):
    if not ANONYMOUS:
        pytest.skip("runs after test_every_operation_without_a_key")
    text = httpx.get(f"{keyed_fuzz_server}/metrics", headers=AUTH).text
    assert metric_value(text, "ffs_auth_refused_total", reason="unauthorized") >= \
        ANONYMOUS[401]


def test_stateful_links_with_a_key(keyed_schema):
    run_stateful(keyed_schema, STEPS, lambda steps: steps_starting(
        "POST /v1/sessions 201", steps) >= 1 and steps_starting("POST /v1/jobs 202", steps) >= 1)

    def steps(prefix: str) -> int:
        return steps_starting(prefix, STEPS)

    assert steps("POST /v1/sessions 201") >= 1, STEPS
    assert steps("POST /v1/jobs 202") >= 1, STEPS
    assert not any(step.endswith(" 401") or step.endswith(" 403") for step in STEPS), STEPS
