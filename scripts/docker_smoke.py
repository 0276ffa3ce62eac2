"""Container checks of scripts/docker-smoke.sh: the tools both check scripts use (podman,
HTTP, meshes and independent truth) and the compose topology's start and its job and session
checks; the single container's checks are scripts/docker_smoke_single.py, the compose run
with API keys scripts/docker_smoke_compose.py.

Standard library only (runs on the host's ``python3``); podman's configuration comes from the
environment (``CONTAINERS_CONF``, ``CONTAINERS_STORAGE_CONF``) set by docker-smoke.sh. All
containers share the host network (no CNI bridge, no firewall rules needed), so every port is
chosen free on the host (:func:`free_port` here, not the test suite's: this runs on the bare
host with no test dependencies, and binds 0.0.0.0 as the containers do); ``scheduler``
resolves to 127.0.0.1 (``--add-host``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import platform
import re
import socket
import subprocess
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

PREFIX = "ffs-smoke"
"""Name prefix of every container the checks start."""
SAMPLES = "service/static/samples"
Mesh = tuple[list[list[float]], list[list[int]]]


class CheckError(AssertionError):
    """A smoke check failed (message says what was expected and what came back)."""


def check(condition: bool, message: str) -> None:
    """Raise :class:`CheckError` with ``message`` unless ``condition``."""
    if not condition:
        raise CheckError(message)


@contextlib.contextmanager
def step(name: str) -> Iterator[None]:
    """Print ``ok <name> (<seconds>)`` or ``FAIL <name>: <why>`` around a block."""
    start = time.monotonic()
    try:
        yield
    except Exception as exc:
        print(f"    FAIL {name}: {type(exc).__name__}: {exc}", flush=True)
        raise
    print(f"    ok   {name} ({time.monotonic() - start:.1f} s)", flush=True)


def note(text: str) -> None:
    """Print an indented detail line under the current step."""
    print(f"         {text}", flush=True)


# -- podman -----------------------------------------------------------------------------------


def podman(*args: str, stdin: bytes | None = None, check_rc: bool = True,
           timeout: float = 120) -> subprocess.CompletedProcess[bytes]:
    """Run ``podman <args>``.

    Args:
        *args: podman's arguments.
        stdin: Bytes for its standard input.
        check_rc: Raise :class:`CheckError` with its stderr when it exits non-zero.
        timeout: Seconds it may take.

    Returns:
        The finished process (output captured).
    """
    proc = subprocess.run(["podman", *args], input=stdin, capture_output=True,
                          timeout=timeout, check=False)
    if check_rc and proc.returncode != 0:
        raise CheckError(f"podman {' '.join(args[:3])} ... exit {proc.returncode}: "
                         f"{proc.stderr.decode(errors='replace').strip()[-2000:]}")
    return proc


def remove_containers(names: list[str]) -> None:
    """Force-remove the named containers (errors ignored: cleanup)."""
    if names:
        podman("rm", "--force", "--time", "2", *names, check_rc=False)


def logs_tail(name: str, lines: int = 40) -> str:
    """The last ``lines`` lines of a container's output."""
    proc = podman("logs", "--tail", str(lines), name, check_rc=False)
    return (proc.stdout + proc.stderr).decode(errors="replace")


def free_port() -> int:
    """A TCP port nobody listens on right now (bound and released on 0.0.0.0)."""
    with socket.socket() as sock:
        sock.bind(("0.0.0.0", 0))
        return int(sock.getsockname()[1])


def port_is_free(port: int) -> bool:
    """Whether ``port`` can be bound on 0.0.0.0."""
    with socket.socket() as sock:
        try:
            sock.bind(("0.0.0.0", port))
        except OSError:
            return False
        return True


# -- HTTP -------------------------------------------------------------------------------------


DEFAULT_HEADERS: dict[str, str] = {}
"""Headers of every request of :func:`http` (the compose checks' API key)."""


def http(method: str, url: str, body: bytes | None = None,
         headers: dict[str, str] | None = None,
         timeout: float = 120) -> tuple[int, dict[str, str], bytes]:
    """One HTTP request.

    Args:
        method: ``GET``, ``POST``, ...
        url: The full URL.
        body: The request body.
        headers: Request headers.
        timeout: Seconds for the answer.

    Returns:
        ``(status, headers with lower-case names, body)``; an HTTP error status is returned,
        not raised.
    """
    request = urllib.request.Request(url, data=body, method=method,
                                     headers={**DEFAULT_HEADERS, **(headers or {})})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return (response.status, {k.lower(): v for k, v in response.headers.items()},
                    response.read())
    except urllib.error.HTTPError as err:
        return err.code, {k.lower(): v for k, v in err.headers.items()}, err.read()


def get_json(url: str, expect: int = 200, **kwargs: Any) -> Any:
    """GET ``url``; check the status and return the decoded JSON body."""
    status, _, body = http("GET", url, **kwargs)
    check(status == expect, f"GET {url}: status {status}, expected {expect}: {body[:500]!r}")
    return json.loads(body)


def post_json(url: str, doc: Any, expect: int = 200,
              accept: str = "application/json") -> tuple[dict[str, str], bytes]:
    """POST a JSON document; check the status; return (headers, body)."""
    status, headers, body = http("POST", url, json.dumps(doc).encode(),
                                 {"Content-Type": "application/json", "Accept": accept})
    check(status == expect, f"POST {url}: status {status}, expected {expect}: {body[:800]!r}")
    return headers, body


def post_form(url: str, fields: dict[str, str], files: dict[str, Path], expect: int,
              accept: str = "application/json") -> tuple[dict[str, str], bytes]:
    """POST multipart/form-data.

    Args:
        url: The full URL.
        fields: Text fields, name -> value.
        files: File fields, name -> path (sent as ``application/octet-stream``).
        expect: The status the answer must have.
        accept: The ``Accept`` header.

    Returns:
        ``(headers, body)`` of the answer.
    """
    boundary = uuid.uuid4().hex
    parts: list[bytes] = []
    for name, value in fields.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n'
                     f"{value}\r\n".encode())
    for name, path in files.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; '
                     f'filename="{path.name}"\r\nContent-Type: application/octet-stream\r\n\r\n'
                     .encode() + path.read_bytes() + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    status, headers, body = http(
        "POST", url, b"".join(parts),
        {"Content-Type": f"multipart/form-data; boundary={boundary}", "Accept": accept})
    check(status == expect, f"POST {url}: status {status}, expected {expect}: {body[:800]!r}")
    return headers, body


def wait_http(url: str, container: str, timeout: float = 180) -> Any:
    """Poll ``url`` until it answers 200.

    Args:
        url: The URL to GET (every 0.5 s).
        container: The container serving it: its end (or ``timeout``) fails the check with
            the end of its log.
        timeout: Seconds to wait at most.

    Returns:
        The decoded JSON of the 200 answer.
    """
    deadline = time.monotonic() + timeout
    while True:
        with contextlib.suppress(OSError, ValueError):
            status, _, body = http("GET", url, timeout=5)
            if status == 200:
                return json.loads(body)
        state = podman("inspect", "--format", "{{.State.Status}}", container,
                       check_rc=False).stdout.decode().strip()
        if state not in ("running", "created", "configured"):
            raise CheckError(f"{container} is {state or 'gone'}:\n{logs_tail(container)}")
        if time.monotonic() > deadline:
            raise CheckError(f"{url} not up after {timeout:.0f} s:\n{logs_tail(container)}")
        time.sleep(0.5)


# -- meshes and independent truth -------------------------------------------------------------


def read_off(path: Path) -> Mesh:
    """Vertices (n, 3) and triangles (m, 3) of an OFF file, as lists."""
    tokens = [line.split("#", 1)[0].split() for line in path.read_text().splitlines()]
    words = [w for line in tokens for w in line]
    check(words[0] == "OFF", f"{path}: not an OFF file")
    n, m = int(words[1]), int(words[2])
    numbers = words[4:]
    vertices = [[float(x) for x in numbers[3 * i:3 * i + 3]] for i in range(n)]
    faces, at = [], 3 * n
    for _ in range(m):
        k = int(numbers[at])
        check(k == 3, f"{path}: only triangles expected")
        faces.append([int(x) for x in numbers[at + 1:at + 4]])
        at += 4
    return vertices, faces


def unique_edges(faces: list[list[int]]) -> list[tuple[int, int]]:
    """The sorted unique undirected edges ``(i, j)``, ``i < j``, of triangles."""
    edges = {tuple(sorted((f[a], f[(a + 1) % 3]))) for f in faces for a in range(3)}
    return sorted(edges)  # type: ignore[arg-type]


def lengths_of(vertices: list[list[float]], edges: list[tuple[int, int]]) -> list[float]:
    """Euclidean length of each edge."""
    return [math.dist(vertices[i], vertices[j]) for i, j in edges]


def max_relative_gap(a: list[float], b: list[float]) -> float:
    """max |a - b| / mean |b| over aligned lists of equal length."""
    check(len(a) == len(b), f"{len(a)} values vs {len(b)}")
    scale = sum(abs(x) for x in b) / len(b)
    return max(abs(x - y) for x, y in zip(a, b, strict=True)) / scale


def expected_backend() -> str:
    """The factorization backend the image must use here: PARDISO wherever MKL exists."""
    return "pardiso" if platform.machine() in ("x86_64", "AMD64") else "superlu"


# -- compose topology -------------------------------------------------------------------------


def compose_services(image: str, root: Path) -> dict[str, Any]:
    """docker-compose.yml's ``services``, parsed by the image's own PyYAML (the host needs
    none)."""
    script = "import json, sys, yaml; json.dump(yaml.safe_load(sys.stdin), sys.stdout)"
    out = podman("run", "--rm", "-i", "--network", "none", image, "python", "-c", script,
                 stdin=(root / "docker-compose.yml").read_bytes()).stdout
    return json.loads(out)["services"]


def substitute(value: str, ports: dict[int, int]) -> str:
    """Replace each port number of ``ports`` (as a whole number) in ``value``."""
    for old, new in ports.items():
        value = re.sub(rf"(?<!\d){old}(?!\d)", str(new), value)
    return value


def run_args(service: dict[str, Any], name: str, ports: dict[int, int]) -> list[str]:
    """``podman run`` arguments for one replica of a compose service (host network).

    Args:
        service: The service's entry of docker-compose.yml, with ``image`` set.
        name: The container's name.
        ports: Port numbers of the compose file -> the free ones used instead (in the
            command, the environment and the healthcheck).

    Returns:
        The arguments after ``podman``.
    """
    args = ["run", "-d", "--name", name, "--network", "host",
            "--add-host", "scheduler:127.0.0.1"]
    if service.get("read_only"):
        args.append("--read-only")
    for path in service.get("tmpfs", []):
        args += ["--tmpfs", path]
    for key, value in (service.get("environment") or {}).items():
        args += ["--env", f"{key}={substitute(str(value), ports)}"]
    health = service.get("healthcheck")
    if health is None or health.get("disable"):
        args.append("--no-healthcheck")  # the image's check probes the API's port 8000
    else:
        test = [substitute(part, ports) for part in health["test"]]
        check(test[0] == "CMD", f"healthcheck test form {test[0]!r} not supported here")
        args += ["--health-cmd", json.dumps(test[1:])]
    return [*args, service["image"], *[substitute(a, ports) for a in service["command"]]]


def wait_healthy(name: str, timeout: float = 120) -> None:
    """Run the container's healthcheck until it passes."""
    deadline = time.monotonic() + timeout
    while podman("healthcheck", "run", name, check_rc=False).returncode != 0:
        if time.monotonic() > deadline:
            raise CheckError(f"{name} not healthy after {timeout:.0f} s:\n{logs_tail(name)}")
        time.sleep(1)


def start_topology(image: str, services: dict[str, Any], api_replicas: int,
                   names: list[str], api_env: dict[str, str] | None = None) -> list[str]:
    """Start the scheduler, its workers and the API replicas, each once it is up.

    Args:
        image: The image every service runs.
        services: docker-compose.yml's ``services``.
        api_replicas: How many API containers.
        names: Gets every started container's name (for the cleanup, also on failure).
        api_env: Environment added to the API replicas' (the API keys).

    Returns:
        The API replicas' base URLs.
    """
    sched, dash = free_port(), free_port()
    ports = {8786: sched, 8787: dash}
    scheduler = dict(services["scheduler"], image=image)
    with step(f"scheduler (port {sched}, dashboard {dash}) healthy"):
        names.append(f"{PREFIX}-scheduler")
        podman(*run_args(scheduler, names[-1], ports))
        wait_healthy(names[-1])
    workers = services["worker"]
    count = int(workers.get("deploy", {}).get("replicas", 1))
    with step(f"{count} worker replicas started"):
        for k in range(count):
            names.append(f"{PREFIX}-worker-{k + 1}")
            podman(*run_args(dict(workers, image=image), names[-1], ports))
    bases = []
    api = dict(services["api"], image=image)
    api["environment"] = {**(api.get("environment") or {}), **(api_env or {})}
    for k in range(api_replicas):
        port = free_port()
        with step(f"API replica {k + 1} on port {port}: GET /healthz"):
            names.append(f"{PREFIX}-api-{k + 1}")
            podman(*run_args(api, names[-1], {**ports, 8000: port}))
            bases.append(f"http://127.0.0.1:{port}")
            wait_http(f"{bases[-1]}/healthz", names[-1])
    with step(f"GET /readyz on both replicas: {count} Dask workers ready"):
        deadline = time.monotonic() + 120
        for base, name in zip(bases, names[-api_replicas:], strict=True):
            while True:
                status, _, body = http("GET", f"{base}/readyz", timeout=10)
                doc = json.loads(body)
                if status == 200 and doc["workers_ready"] >= count:
                    break
                if time.monotonic() > deadline:
                    raise CheckError(f"{base}/readyz: {status} {doc}\n{logs_tail(name)}")
                time.sleep(1)
        note(f"readyz: {doc}")
    return bases


def check_job_across_replicas(first: str, second: str, root: Path) -> None:
    """A job submitted through ``first`` is polled and fetched through ``second``."""
    mesh_path = root / SAMPLES / "torus.off"
    vertices, faces = read_off(mesh_path)
    edges = unique_edges(faces)
    with step("job submitted via replica 1, polled and fetched via replica 2"):
        headers, _ = post_form(f"{first}/v1/jobs", {"operation": "reconstruct"},
                                  {"file": mesh_path}, 202)
        location = headers.get("location")
        check(bool(location), f"no Location header: {headers}")
        deadline = time.monotonic() + 180
        while (job := get_json(f"{second}{location}"))["status"] in ("queued", "running"):
            check(time.monotonic() < deadline, f"job still {job['status']} after 180 s")
            time.sleep(0.3)
        check(job["status"] == "succeeded", f"job {job['status']}: {job.get('error')}")
        result = get_json(f"{second}{location}/result")
        gap = max_relative_gap(lengths_of(result["vertices"], edges),
                               lengths_of(vertices, edges))
        check(gap < 1e-6, f"job result's edge lengths off by {gap:.2e}")
        note(f"{location}: succeeded, {len(result['vertices'])} vertices, edge lengths match "
             f"the file's (max gap {gap:.1e}), backend {result['report'].get('backend')!r}")


def check_session_across_replicas(first: str, second: str, root: Path) -> None:
    """A deformation session created through ``first`` is dragged through ``second``."""
    vertices, faces = read_off(root / SAMPLES / "face.off")
    n = len(vertices)
    handles = [0, n // 2, n - 1]
    with step("deformation session created via replica 1, dragged via replica 2"):
        doc = {"vertices": vertices, "faces": faces,
               "handles": [{"vertex": h} for h in handles]}
        headers, body = post_json(f"{first}/v1/sessions", doc, expect=201)
        info = json.loads(body)
        check(info["executor"] == "dask", f"session executor {info['executor']!r}")
        check(info["backend"] == expected_backend(), f"session backend {info['backend']!r}")
        location = headers["location"]
        for step_k, lift in enumerate((0.0, 0.1), start=1):
            targets = [[x, y, z + (lift if h == handles[1] else 0.0)]
                       for h in handles for x, y, z in [vertices[h]]]
            _, body = post_json(f"{second}{location}/solve", {"handle_positions": targets})
            moved = json.loads(body)["vertices"]
            check(len(moved) == n, f"{len(moved)} vertices back, expected {n}")
            miss = max(math.dist(moved[h], t) for h, t in zip(handles, targets, strict=True))
            rest = max(math.dist(a, b) for a, b in zip(moved, vertices, strict=True))
            size = max(math.dist(vertices[0], v) for v in vertices)
            check(miss < 1e-3 * size, f"drag {step_k}: handles {miss:.2e} from their targets")
            if lift == 0.0:
                check(rest < 1e-6 * size, f"drag to the rest pose moved vertices by {rest:.2e}")
            else:
                check(rest > 0.5 * lift, f"lifting a handle by {lift} moved vertices by {rest}")
        # Each replica reports its drags to the scheduler's registry at most once a second.
        deadline = time.monotonic() + 15
        while (state := get_json(f"{first}{location}"))["solves"] < 2:
            check(time.monotonic() < deadline,
                  f"session reports {state['solves']} solves after 15 s, expected 2")
            time.sleep(0.5)
        check(state["solves"] == 2, f"session reports {state['solves']} solves, expected 2")
        status, _, _ = http("DELETE", f"{second}{location}")
        check(status == 204, f"DELETE: status {status}")
        status, _, _ = http("GET", f"{first}{location}")
        check(status == 404, f"closed session still answers {status}")
        note(f"{location}: {n} vertices, backend {info['backend']!r}, handles {handles} on "
             "target after each drag, 2 solves, closed")


def run_checks(checks: Callable[[str, Path], None], description: str) -> int:
    """The command line of a check script: ``--image`` and ``--root``.

    Args:
        checks: ``checks(image, root)``; raises (after printing what failed) on failure.
        description: The ``--help`` text.

    Returns:
        The exit status: 0 when every check passed, 1 otherwise.
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--image", required=True)
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    args = parser.parse_args()
    try:
        checks(args.image, args.root)
    except Exception:
        return 1
    return 0
