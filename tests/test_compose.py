"""docker-compose.yml checks that need no Docker engine: it builds the one image of the
Dockerfile, runs the README's serve command for the API, and wires the API, the scheduler
and the workers together with settings the service really reads."""

from __future__ import annotations

import importlib
import json
import re

import yaml

from scripts import docker_smoke
from service.settings import Settings
from tests.helpers import REPO

COMPOSE = yaml.safe_load((REPO / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]


def _dockerfile_cmd() -> list[str]:
    text = (REPO / "Dockerfile").read_text()
    (cmd,) = re.findall(r"^CMD (\[.*\])$", text, re.MULTILINE)
    return json.loads(cmd)


def test_one_image_for_every_service():
    images = {s["image"] for s in SERVICES.values()}
    assert len(images) == 1
    assert all(s["build"] == "." for s in SERVICES.values())
    assert set(SERVICES) == {"api", "scheduler", "worker"}


def test_api_runs_the_image_command_on_the_scheduler():
    api = SERVICES["api"]
    assert api["command"] == _dockerfile_cmd()
    assert " ".join(api["command"]) in (REPO / "README.md").read_text()
    env = {k: str(v) for k, v in api["environment"].items()}
    settings = Settings(**{k.removeprefix("FFS_").lower(): v for k, v in env.items()})
    assert settings.executor == "dask"
    scheduler = SERVICES["scheduler"]["command"]
    port = scheduler[scheduler.index("--port") + 1]
    assert settings.dask_scheduler_address == f"tcp://scheduler:{port}"
    assert SERVICES["worker"]["command"][:3] == ["dask", "worker", f"tcp://scheduler:{port}"]
    (published,) = api["ports"]
    assert published.rsplit(":", 1)[1] == str(settings.port)  # the container port it serves


def _host_ports(published: str) -> range:
    """``"8000-8003:8000"`` -> range(8000, 8004); ``"8000:8000"`` -> range(8000, 8001)."""
    host = published.rsplit(":", 1)[0].rsplit(":", 1)[-1]  # drop a container port, a host IP
    low, _, high = host.partition("-")
    return range(int(low), int(high or low) + 1)


def test_scaled_api_replicas_fit_the_published_ports():
    """Every ``--scale api=N`` that the docs and the compose file show has N host ports to
    publish on (a single fixed port would make the second replica fail to start)."""
    (published,) = SERVICES["api"]["ports"]
    ports = _host_ports(published)
    assert ports.start == 8000  # the port the README and docs/distributed.md name
    texts = [(REPO / name).read_text() for name in
             ("docker-compose.yml", "README.md", "docs/distributed.md", "docs/deployment.md")]
    scales = [int(n) for text in texts for n in re.findall(r"--scale api=(\d+)", text)]
    assert scales, "no --scale api=N example left: say how API replicas scale"
    assert max(scales) <= len(ports), (scales, published)
    assert f"up to {len(ports)} replicas" in (REPO / "docs" / "distributed.md").read_text()


def test_scheduler_preload_and_retry_policy():
    scheduler = SERVICES["scheduler"]
    module = scheduler["command"][scheduler["command"].index("--preload") + 1]
    assert hasattr(importlib.import_module(module), "dask_setup")
    assert scheduler["environment"]["DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES"] == "1"
    worker = SERVICES["worker"]
    assert worker["command"][worker["command"].index("--nthreads") + 1] == "1"
    assert worker["deploy"]["replicas"] >= 2
    for name in ("scheduler", "worker"):  # the image's HEALTHCHECK probes the API port
        assert "healthcheck" in SERVICES[name]


def test_documented():
    doc = (REPO / "docs" / "distributed.md").read_text()
    assert "docker compose up --build --scale worker=4" in doc
    assert "docker compose up --build" in (REPO / "README.md").read_text()


def test_smoke_script_runs_every_service_as_composed():
    """The smoke test's podman arguments carry each service's command, environment,
    read-only root, tmpfs and healthcheck, with only the port numbers moved."""
    ports = {8786: 41001, 8787: 41002, 8000: 41003}
    for name, service in SERVICES.items():
        args = docker_smoke.run_args(service, f"x-{name}", ports)
        image_at = args.index(service["image"])
        command = args[image_at + 1:]
        expected = [str(a).replace("8786", "41001").replace("8787", "41002")
                    .replace("8000", "41003") for a in service["command"]]
        assert command == expected
        assert ("--read-only" in args) == bool(service.get("read_only"))
        assert args[args.index("--tmpfs") + 1] == "/tmp"
        env = {args[i + 1].split("=", 1)[0]: args[i + 1].split("=", 1)[1]
               for i, a in enumerate(args[:image_at]) if a == "--env"}
        assert set(env) == set(service.get("environment") or {})
        health = service.get("healthcheck", {})
        if health.get("disable") or not health:
            assert "--no-healthcheck" in args
        else:
            test = json.loads(args[args.index("--health-cmd") + 1])
            assert test == [t.replace("8786", "41001") for t in health["test"][1:]]
    api = docker_smoke.run_args(SERVICES["api"], "x", ports)
    assert "FFS_DASK_SCHEDULER_ADDRESS=tcp://scheduler:41001" in api
    assert api[api.index("--add-host") + 1] == "scheduler:127.0.0.1"
