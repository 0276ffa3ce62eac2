"""Schemathesis against a real uvicorn: every operation of openapi/openapi.json with generated
inputs (JSON, multipart and ``application/vnd.ffs.arrays`` bodies), then stateful runs that
follow the document's links (session create -> solve, state, delete; job submit -> status,
result, cancel). Any 5xx, or a response whose status, content type, headers or body the
document does not describe, fails the test.

Binary bodies: the document describes them as bytes (their layout is in words), so the run
generates each operation's JSON body for them instead and :func:`_arrays_body` encodes it as
the binary format: its large arrays as raw bytes of a dtype chosen from the allowed ones, the
rest as the header. Generated values that are no numeric array stay in the header (a 422).

Bounded: a fixed number of examples per operation and of stateful steps (about a minute and
a half on a contended 2-core machine).
"""

from __future__ import annotations

import copy
import json
import os
import time
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from hypothesis.errors import FlakyFailure, FlakyStrategyDefinition
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from schemathesis.specs.openapi.checks import use_after_free

from service.api.decoding import BINARY_DTYPES, BINARY_MAGIC, BINARY_MEDIA_TYPE
from service.operations import OPERATIONS
from tests.helpers.servers import uvicorn_server
from tests.helpers.service import metric_value

ARRAYS = {f"/v1/{name}": spec.arrays for name, spec in OPERATIONS.items()}
"""Path -> the large arrays of its body (those a binary body sends as bytes)."""
STEPS: Counter[str] = Counter()
SENT: Counter[str] = Counter()
"""Binary bodies sent, by how they went out (``arrays``: at least one array as bytes)."""


def _padded(data: bytes) -> bytes:
    return data + b"\0" * (-len(data) % 8)


def _as_array(value: Any, integer: bool, variant: int) -> np.ndarray | None:
    """``value`` as a numeric array of one of the binary dtypes, or None when it is none
    (ragged, strings, null, integers beyond 64 bits)."""
    try:
        array = np.asarray(value)
    except (ValueError, OverflowError):
        return None
    if array.dtype.kind == "b" or array.dtype.kind not in "iuf" or array.ndim > 3:
        return None
    if array.dtype.kind in "iu" and integer:
        candidates = [d for d in ("<i4", "<u4", "<i8") if np.can_cast(
            np.min_scalar_type(array.min() if array.size else 0), d)
            and np.can_cast(np.min_scalar_type(array.max() if array.size else 0), d)]
        return array.astype(candidates[variant % len(candidates)]) if candidates else None
    with np.errstate(over="ignore"):  # f4 may overflow: inf, a 422
        return array.astype(("<f8", "<f4")[variant % 2])


def _arrays_body(path: str, value: Any) -> bytes:
    """A generated JSON body (or any generated value) as an ``application/vnd.ffs.arrays``
    body, encoded here from the layout in docs/service.md (independently of ffs_wire.arrays)."""
    if isinstance(value, bytes):  # generated as raw bytes: sent as they are
        SENT["raw"] += 1
        return value
    header: Any = copy.copy(value)
    meta, parts = {}, []
    if isinstance(header, dict):
        for k, (name, spec) in enumerate(ARRAYS.get(path, {}).items()):
            if name in header:
                array = _as_array(header[name], spec.integer, len(header[name]) + k
                                  if isinstance(header[name], list) else k)
                if array is not None:
                    del header[name]
                    meta[name] = {"dtype": array.dtype.str, "shape": list(array.shape)}
                    parts.append(_padded(np.ascontiguousarray(array).tobytes()))
        header["arrays"] = meta
    assert all(d["dtype"] in BINARY_DTYPES for d in meta.values())
    SENT["arrays" if meta else "header only"] += 1
    text = json.dumps(header, separators=(",", ":"), allow_nan=True).encode()
    return _padded(BINARY_MAGIC + len(text).to_bytes(4, "little") + text) + b"".join(parts)


@schemathesis.serializer(BINARY_MEDIA_TYPE)
def _binary(ctx, value) -> bytes:
    return _arrays_body(ctx.case.operation.path, value)


def binary_as_json_body(doc: dict[str, Any]) -> dict[str, Any]:
    """``doc`` with every binary body described by its operation's JSON body schema (so that
    the generated values are bodies with arrays, which :func:`_arrays_body` encodes)."""
    doc = copy.deepcopy(doc)
    for operations in doc["paths"].values():
        for operation in operations.values():
            content = operation.get("requestBody", {}).get("content", {})
            if BINARY_MEDIA_TYPE in content and "application/json" in content:
                content[BINARY_MEDIA_TYPE] = copy.deepcopy(content["application/json"])
    return doc


CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_headers_conformance, response_schema_conformance]
EXAMPLES = int(os.environ.get("FFS_FUZZ_EXAMPLES", "20"))
"""Examples per operation (a deeper run: FFS_FUZZ_EXAMPLES=500)."""
STATEFUL_EXAMPLES = int(os.environ.get("FFS_FUZZ_STATEFUL", "50"))
"""Stateful runs per step count of :data:`STATEFUL_STEPS` (fewer reached no session solve in
some environments: 25 followed none in a fresh venv with hypothesis 6.170, 50 followed ten)."""
STATEFUL_STEPS = (8, 12, 16)
"""Steps of each stateful run, tried in turn until the links asserted were reached (each a
different derandomized exploration): a job's links are followed only after a generated job
body is valid, about one POST /v1/jobs in thirty, and with the job and session lists and
the shape-space uploads among the operations a single run of 8 steps reached no job (or no
session) in some whole-suite runs (hypothesis 6.170)."""
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
    doc = httpx.get(f"{fuzz_server}/openapi.json", timeout=30).json()
    schema = schemathesis.openapi.from_dict(binary_as_json_body(doc))
    schema.config.update(base_url=fuzz_server)
    return schema


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.exclude(path=SKIP[0]).parametrize()
@SETTINGS
def test_every_operation_matches_the_document(case):
    response = case.call_and_validate(checks=CHECKS, timeout=60)
    if case.media_type == BINARY_MEDIA_TYPE:
        SENT[f"status {response.status_code // 100}xx"] += 1


def test_binary_bodies_were_sent():
    """The run above sent binary bodies, and some of them were well-formed enough to be
    answered (2xx) rather than all refused at the framing (a generator that only sends
    garbage would test nothing past the header)."""
    if not SENT:
        pytest.skip("runs after test_every_operation_matches_the_document")
    print("binary bodies:", dict(SENT))
    assert SENT["arrays"] >= 20 and SENT["status 2xx"] >= 3, SENT


def _no_sessions(base: str) -> None:
    deadline = time.monotonic() + 30
    while metric_value(httpx.get(f"{base}/metrics").text, "ffs_sessions") > 0:
        assert time.monotonic() < deadline, "sessions did not expire"
        time.sleep(0.2)


def run_stateful(schema, steps: Counter[str],
                 reached: Callable[[Counter[str]], bool] = lambda steps: True) -> None:
    """Follow ``schema``'s links as a state machine (:data:`STATEFUL_EXAMPLES` runs of
    :data:`STATEFUL_STEPS` steps, the next step count only while ``reached(steps)`` is
    False), every response checked (:data:`CHECKS` and ``use_after_free``) and counted in
    ``steps`` as ``"METHOD path status"``."""
    for step_count in STATEFUL_STEPS:
        _run_machine(schema, steps, step_count)
        if reached(steps):
            return


def _run_machine(schema, steps: Counter[str], step_count: int) -> None:
    machine = schema.as_state_machine()

    class Checked(machine):  # type: ignore[misc, valid-type]
        def validate_response(self, response, case, **kwargs):
            steps[f"{case.method} {case.operation.path} {response.status_code}"] += 1
            try:
                case.validate_response(response, checks=[*CHECKS, use_after_free])
            except BaseException as exc:
                failures.append(f"{case.method} {case.formatted_path}: {exc}")
                raise

    failures: list[str] = []
    try:
        Checked.run(settings=settings(max_examples=STATEFUL_EXAMPLES,
                                      stateful_step_count=step_count,
                                      deadline=None, derandomize=True,
                                      suppress_health_check=list(HealthCheck), database=None))
    except (FlakyStrategyDefinition, FlakyFailure) as exc:
        # Hypothesis replays a step sequence and finds other rules available: the links
        # it may follow depend on the live server's answers (a 201 one time, a 429 the
        # next). Not a failure of the service, as long as no check failed. Newer
        # hypothesis wraps it in a FlakyFailure group (CI, stop 51): only that group whose
        # every member is such a replay mismatch is let through.
        if not only_replay_mismatches(exc):
            raise
        assert not failures, failures


def only_replay_mismatches(exc: BaseException) -> bool:
    """True when ``exc`` is a :class:`FlakyStrategyDefinition`, or a group (at any depth)
    holding nothing else: a replayed step sequence drew other values, nothing failed."""
    if isinstance(exc, BaseExceptionGroup):
        return all(only_replay_mismatches(member) for member in exc.exceptions)
    return isinstance(exc, FlakyStrategyDefinition)


def steps_starting(prefix: str, steps: Counter[str]) -> int:
    """The requests of ``steps`` (:func:`run_stateful`) whose ``"METHOD path status"``
    starts with ``prefix``."""
    return sum(n for step, n in steps.items() if step.startswith(prefix))


def _links_followed(steps: Counter[str]) -> bool:
    """Sessions created, solved and deleted, jobs submitted and one's status, result or
    mesh answered 200: what :func:`test_stateful_links` asserts."""
    def count(prefix: str) -> int:
        return steps_starting(prefix, steps)

    return (count("POST /v1/sessions 201") >= 1
            and count("POST /v1/sessions/{session_id}/solve ") >= 1
            and count("DELETE /v1/sessions/{session_id} 204") >= 1
            and count("POST /v1/jobs 202") >= 1
            and sum(count(f"GET /v1/jobs/{{job_id}}{link} 200")
                    for link in ("", "/result", "/mesh")) >= 1)


def test_stateful_links(api_schema, fuzz_server):
    _no_sessions(fuzz_server)
    run_stateful(api_schema, STEPS, _links_followed)
    print(f"stateful: {sum(STEPS.values())} requests", dict(STEPS))
    # The links were followed (by the state machine itself, counted in STEPS): sessions
    # were created, solved and deleted through them, jobs submitted and followed.
    def steps(prefix: str) -> int:
        return steps_starting(prefix, STEPS)

    assert steps("POST /v1/sessions 201") >= 1, STEPS
    assert steps("POST /v1/sessions/{session_id}/solve ") >= 1, STEPS
    assert steps("DELETE /v1/sessions/{session_id} 204") >= 1, STEPS
    assert steps("POST /v1/jobs 202") >= 1, STEPS
    # A job's links: its status, result or mesh answered 200 (which of them the machine
    # follows after a job finished depends on the server's timing: in one run it followed
    # only /mesh to a 200, and /result while the job still ran, 409).
    assert sum(steps(f"GET /v1/jobs/{{job_id}}{link} 200")
               for link in ("", "/result", "/mesh")) >= 1, STEPS
