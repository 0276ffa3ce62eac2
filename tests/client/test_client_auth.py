"""API keys in the Python client and the command line (issue 46) against a real uvicorn with
keys: ``Client(url, token=...)`` and ``$FFS_TOKEN`` on HTTP and the sessions' WebSocket,
typed 401/403 errors, another key's session as NotFoundError; ``ffs --server ... --token`` and
``FFS_TOKEN``, and the hint a command prints without a key."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator

import numpy as np
import pytest

from ffs import Client, ForbiddenError, NotFoundError, UnauthorizedError
from tests.helpers import DATA, REPO
from tests.helpers.meshes import icosphere
from tests.helpers.servers import uvicorn_process

KEYS = {"alice": "alice-client-key-0123456789", "bob": "bob-client-key-0123456789"}


@pytest.fixture(scope="module")
def keyed_server() -> Iterator[str]:
    with uvicorn_process({"FFS_WORKERS": "1", "FFS_API_KEYS": json.dumps(KEYS)}) as (base, _):
        yield base


def test_the_client_sends_its_token_on_http_and_websocket(keyed_server, monkeypatch):
    V, F = icosphere(2)
    monkeypatch.delenv("FFS_TOKEN", raising=False)
    with Client(keyed_server, retries=0) as anonymous:
        with pytest.raises(UnauthorizedError) as refused:
            anonymous.fundamental_forms(V, F)
        assert refused.value.status == 401 and refused.value.kind == "unauthorized"
    with Client(keyed_server, token=KEYS["alice"]) as alice:
        forms = alice.fundamental_forms(V, F)
        assert len(forms.lengths) == len(forms.edges)
        with pytest.raises(ForbiddenError):
            alice.request("GET", "/metrics")
        handles = [0, 10, 20]
        with alice.session(V, F, handles) as session:
            assert session.transport == "ws"  # the handshake carried the key
            moved = session.drag(V[handles] + [0.0, 0.0, 0.05])
            assert moved.shape == V.shape and np.abs(moved[handles] - V[handles]
                                                     - [0, 0, 0.05]).max() < 1e-3
            with Client(keyed_server, token=KEYS["bob"]) as bob, pytest.raises(NotFoundError):
                bob.request("GET", f"/v1/sessions/{session.id}")
    monkeypatch.setenv("FFS_TOKEN", KEYS["bob"])
    with Client(keyed_server) as bob:
        job = bob.submit("forms", V, F)
        assert len(job.result().edges) == len(forms.edges)


def _ffs(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    full = {k: v for k, v in os.environ.items() if k not in ("FFS_SERVER", "FFS_TOKEN")}
    full["PYTHONPATH"] = str(REPO)
    return subprocess.run([sys.executable, "-m", "ffs", *args], capture_output=True,
                          text=True, timeout=300, env={**full, **(env or {})}, cwd=REPO)


def test_the_command_line_takes_a_token(keyed_server, tmp_path):
    mesh = str(DATA / "torus.off")
    out = tmp_path / "forms.json"
    refused = _ffs("forms", mesh, "-o", str(out), "--server", keyed_server, "-q")
    assert refused.returncode == 1 and not out.exists()
    assert "--token or FFS_TOKEN" in refused.stderr + refused.stdout
    given = _ffs("forms", mesh, "-o", str(out), "--server", keyed_server, "-q",
                 "--token", KEYS["alice"])
    assert given.returncode == 0, given.stderr
    assert json.loads(out.read_text())["edges"]
    out.unlink()
    from_env = _ffs("forms", mesh, "-o", str(out), "--server", keyed_server, "-q",
                    env={"FFS_TOKEN": KEYS["bob"]})
    assert from_env.returncode == 0, from_env.stderr
    assert KEYS["bob"] not in from_env.stdout + from_env.stderr
