"""The Docker smoke test's checks with API keys (scripts/docker_smoke_compose.py) run here
against what they meet in the compose topology, without a container engine: two real uvicorn
replicas with the script's environment (:func:`api_environment`) on one Dask cluster and the
script's webhook receiver on loopback. So the checks that podman runs rarely are known to
pass (and to check what they say) whenever the suite runs."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Iterator
from types import ModuleType

import dask
import pytest
from distributed import LocalCluster

from tests.helpers import REPO
from tests.helpers.servers import server_log, uvicorn_process


@pytest.fixture(scope="module")
def smoke() -> Iterator[ModuleType]:
    scripts = str(REPO / "scripts")
    sys.path.insert(0, scripts)  # the script imports its tools as the host runs it
    try:
        yield importlib.import_module("docker_smoke_compose")
    finally:
        sys.path.remove(scripts)


def test_the_compose_key_checks_pass_on_two_replicas(smoke: ModuleType) -> None:
    receiver = smoke.Receiver()
    try:
        with dask.config.set({"distributed.scheduler.allowed-failures": 1}), LocalCluster(
                n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                dashboard_address=":0", worker_dashboard_address=None) as cluster:
            env = {"FFS_EXECUTOR": "dask", "FFS_WORKERS": "2",
                   "FFS_DASK_SCHEDULER_ADDRESS": cluster.scheduler_address,
                   **smoke.api_environment(receiver.port)}
            with uvicorn_process(env, log_level="info") as (a, _), \
                    uvicorn_process(env, log_level="info") as (b, _):
                smoke.check_keys_across_replicas(a, b, REPO)
                smoke.check_quota_across_replicas(a, b, REPO)
                smoke.check_webhook(a, b, REPO, receiver)
                logs = [server_log(base).read_text() for base in (a, b)]
    finally:
        receiver.close()
        smoke.DEFAULT_HEADERS.clear()
    assert [r["method"] for r in receiver.requests] == ["POST", "POST"]
    for log in logs:  # what check_no_key_in_logs looks for in the containers' output
        assert "GET /v1/jobs" in log
        for key in (*smoke.KEYS.values(), smoke.WRONG_KEY):
            assert key not in log
