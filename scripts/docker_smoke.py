"""Container checks for scripts/docker-smoke.sh: run the built image with podman, test it over HTTP.

Standard library only (runs on the host's ``python3``); podman's configuration comes from the
environment (``CONTAINERS_CONF``, ``CONTAINERS_STORAGE_CONF``) set by docker-smoke.sh. All
containers share the host network (no CNI bridge, no firewall rules needed), so every port is
chosen free on the host; ``scheduler`` resolves to 127.0.0.1 (``--add-host``).

``single``
    One container with the image's own CMD and HEALTHCHECK (FFS_PORT moved when 8000 is
    taken; FFS_BODY_TIMEOUT=5): ``/healthz``; a client trickling its request head is
    answered 408 and cut off after FFS_HEADER_TIMEOUT, one trickling its body after a complete
    head gets the 408 ``body-timeout`` problem after FFS_BODY_TIMEOUT; ``/v1/forms`` of a
    mesh file against edge lengths computed here; exact forms reconstructed (lengths match
    the file's); perturbed, non-integrable forms reconstructed by least squares with the
    PARDISO backend; a GLB that the Khronos validator (tools/gltf-validator) accepts; the web
    page, every module of its import map and every vendored three.js file; the MKL libraries
    the solver process has mapped.
``compose``
    docker-compose.yml's services (command, environment, read-only root, tmpfs,
    healthcheck, replicas) from the same image: the scheduler (waited for until healthy),
    its worker replicas and two API replicas; a job submitted through one API replica is
    polled and fetched through the other; a deformation session created through one is
    dragged through the other and closed.

Exit status 0 when every check passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import platform
import re
import select
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

PREFIX = "ffs-smoke"
HEADER_TIMEOUT = 10.0
"""FFS_HEADER_TIMEOUT's default (service/settings.py), unless the image sets it."""
BODY_TIMEOUT = 5.0
"""FFS_BODY_TIMEOUT of the single container (its default, 60 s, would make the check last a
minute; the value only sets how long the trickled body is waited for)."""
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
    """Run ``podman <args>``; raise with its stderr when it fails and ``check_rc``."""
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


def http(method: str, url: str, body: bytes | None = None,
         headers: dict[str, str] | None = None,
         timeout: float = 120) -> tuple[int, dict[str, str], bytes]:
    """One request; returns (status, headers with lower-case names, body), never raises on
    an HTTP error status."""
    request = urllib.request.Request(url, data=body, method=method, headers=headers or {})
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
    """POST multipart/form-data (text ``fields`` and ``files``); check the status."""
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
    """Poll ``url`` until it answers 200 (JSON); fail early if ``container`` stopped."""
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


def validate_glb(root: Path, glb: bytes) -> dict[str, Any]:
    """The Khronos glTF-Validator's report on ``glb`` (installs it with npm ci if missing)."""
    folder = root / "tools" / "gltf-validator"
    node, npm = shutil.which("node"), shutil.which("npm")
    check(node is not None and npm is not None, "node and npm are needed for the validator")
    if not (folder / "node_modules" / "gltf-validator" / "package.json").is_file():
        subprocess.run([npm, "ci", "--silent", "--no-audit", "--no-fund", "--prefix",
                        str(folder)], check=True, timeout=600)
    proc = subprocess.run([node, str(folder / "validate.mjs"), "--format", "glb",
                           "--max-issues", "0", "-"], input=glb, capture_output=True,
                          timeout=300, check=False)
    check(proc.returncode == 0, f"validator exit {proc.returncode}: {proc.stderr[-1000:]!r}")
    return json.loads(proc.stdout)


def expected_backend() -> str:
    """The factorization backend the image must use here: PARDISO wherever MKL exists."""
    return "pardiso" if platform.machine() in ("x86_64", "AMD64") else "superlu"


# -- single container -------------------------------------------------------------------------


def image_cmd(image: str) -> list[str]:
    """The image's CMD (argv)."""
    out = podman("image", "inspect", "--format", "{{json .Config.Cmd}}", image).stdout
    return json.loads(out)


def image_env(image: str) -> dict[str, str]:
    """The image's ENV (name -> value)."""
    out = podman("image", "inspect", "--format", "{{json .Config.Env}}", image).stdout
    return dict(item.split("=", 1) for item in json.loads(out))


def trickle(base: str, first: bytes, limit: float) -> tuple[bytes, int, float | None]:
    """Send ``first`` on a new connection, then one more byte every 0.5 s (slow-loris) until
    the server closes it or ``limit`` s pass; after the 4th byte another client must get
    /healthz. Returns (what the server answered, bytes trickled, seconds until it closed)."""
    host, port = base.removeprefix("http://").rsplit(":", 1)
    sock = socket.create_connection((host, int(port)), timeout=5)
    with sock:
        start = time.monotonic()
        sock.sendall(first)
        sock.setblocking(False)
        received, sent, closed_at = b"", 0, None
        while time.monotonic() - start < limit:
            ready, _, _ = select.select([sock], [], [], 0.5)
            if ready:
                try:
                    chunk = sock.recv(4096)
                except ConnectionResetError:  # closed with our trickled bytes unread
                    chunk = b""
                if not chunk:
                    closed_at = time.monotonic() - start
                    break
                received += chunk
                continue
            with contextlib.suppress(OSError):  # the server may have closed already
                sock.send(b"a")
                sent += 1
            if sent == 4:  # meanwhile the server answers others
                status, _, _ = http("GET", f"{base}/healthz", timeout=5)
                check(status == 200, f"/healthz during the trickle: {status}")
    return received, sent, closed_at


def check_header_timeout(base: str, timeout: float) -> None:
    """A client that trickles its request head (one byte every 0.5 s, slow-loris) gets 408
    and a closed connection ``timeout`` seconds after its first byte, while another client
    is served meanwhile."""
    with step(f"a head trickled at 2 bytes/s is cut off with 408 after ~{timeout:g} s"):
        received, sent, closed_at = trickle(
            base, b"GET /healthz HTTP/1.1\r\nHost: smoke\r\nX-Slow: ", timeout + 10)
        check(closed_at is not None, f"connection still open after {timeout + 10:g} s "
                                     f"({sent} bytes trickled)")
        check(received.startswith(b"HTTP/1.1 408"), f"answer {received[:80]!r}")
        check(timeout - 0.5 <= closed_at <= timeout + 3,
              f"closed after {closed_at:.1f} s, FFS_HEADER_TIMEOUT={timeout:g}")
        note(f"408 and closed after {closed_at:.1f} s ({sent} header bytes trickled)")


def check_body_timeout(base: str, timeout: float) -> None:
    """A client that sends a complete head (Content-Length 1000) and then trickles the body
    (one byte every 0.5 s) gets the 408 ``body-timeout`` problem and a closed connection
    FFS_BODY_TIMEOUT after its head, while another client is served meanwhile."""
    with step(f"a body trickled at 2 bytes/s is cut off with 408 body-timeout after "
              f"~{timeout:g} s"):
        head = (b"POST /v1/forms HTTP/1.1\r\nHost: smoke\r\nContent-Type: application/json"
                b"\r\nContent-Length: 1000\r\n\r\n{")
        received, sent, closed_at = trickle(base, head, timeout + 10)
        check(closed_at is not None, f"connection still open after {timeout + 10:g} s "
                                     f"({sent} body bytes trickled)")
        status_line, _, rest = received.partition(b"\r\n")
        check(status_line.startswith(b"HTTP/1.1 408"), f"answer {received[:80]!r}")
        doc = json.loads(rest.partition(b"\r\n\r\n")[2] or b"{}")
        check(doc.get("kind") == "body-timeout" and doc.get("status") == 408,
              f"problem document {doc}")
        check(timeout - 0.5 <= closed_at <= timeout + 3,
              f"closed after {closed_at:.1f} s, FFS_BODY_TIMEOUT={timeout:g}")
        note(f"408 body-timeout and closed after {closed_at:.1f} s ({sent} body bytes "
             f"trickled): {doc.get('detail')}")


def check_forms_and_reconstruct(base: str, root: Path) -> None:
    """/v1/forms, exact reconstruction, PARDISO least squares, GLB (prints each step)."""
    mesh_path = root / SAMPLES / "torus.off"
    vertices, faces = read_off(mesh_path)
    edges = unique_edges(faces)
    truth = lengths_of(vertices, edges)
    with step(f"POST /v1/forms ({mesh_path.name}: {len(vertices)} vertices, {len(faces)} faces)"):
        _, body = post_form(f"{base}/v1/forms", {}, {"file": mesh_path}, 200)
        forms = json.loads(body)
        check([tuple(e) for e in forms["edges"]] == edges, "edges differ from the file's")
        gap = max_relative_gap(forms["lengths"], truth)
        check(gap < 1e-9, f"lengths differ from the file's by {gap:.2e}")
        note(f"{len(edges)} edges; lengths match the file's (max gap {gap:.1e})")
    with step("POST /v1/reconstruct (exact forms) -> JSON"):
        _, body = post_json(f"{base}/v1/reconstruct", forms)
        result = json.loads(body)
        check(len(result["vertices"]) == len(vertices), "vertex count differs")
        gap = max_relative_gap(lengths_of(result["vertices"], edges), truth)
        check(gap < 1e-6, f"reconstructed edge lengths off by {gap:.2e}")
        note(f"edge lengths of the result match the file's (max gap {gap:.1e}); "
             f"backend {result['report'].get('backend')!r}")
    with step("POST /v1/reconstruct (perturbed, non-integrable forms) -> PARDISO"):
        noisy = dict(forms, lengths=[x * (1 + 0.02 * math.sin(7.0 * k))
                                     for k, x in enumerate(forms["lengths"])])
        _, body = post_json(f"{base}/v1/reconstruct", noisy)
        report = json.loads(body)["report"]
        integrable = report.get("integrability", {}).get("integrable")
        check(integrable is False, f"perturbed forms reported integrable={integrable!r}")
        expected = expected_backend()
        check(report.get("backend") == expected,
              f"backend {report.get('backend')!r}, expected {expected!r}")
        note(f"integrable=False, backend {report['backend']!r}")
    with step("POST /v1/reconstruct (face.off, Accept: model/gltf-binary) -> Khronos validator"):
        face_path = root / SAMPLES / "face.off"
        face_v, face_f = read_off(face_path)
        headers, glb = post_form(f"{base}/v1/reconstruct?color=defect", {},
                                 {"file": face_path}, 200, accept="model/gltf-binary")
        check(glb[:4] == b"glTF", f"not a GLB: {glb[:16]!r}")
        check(headers.get("content-type", "").startswith("model/gltf-binary"),
              f"content-type {headers.get('content-type')!r}")
        report = validate_glb(root, glb)
        issues, info = report["issues"], report["info"]
        check(issues["numErrors"] == 0, f"validator errors: {issues['messages'][:5]}")
        check(info["totalTriangleCount"] == len(face_f),
              f"{info['totalTriangleCount']} triangles, expected {len(face_f)}")
        check(info["totalVertexCount"] == len(face_v),
              f"{info['totalVertexCount']} vertices, expected {len(face_v)}")
        note(f"{len(glb)} bytes, {issues['numErrors']} errors, {issues['numWarnings']} "
             f"warnings, {info['totalTriangleCount']} triangles")


def check_web(base: str, root: Path) -> None:
    """The page, its import map targets, the vendored three.js files (vs web/node_modules)."""
    with step("GET / and its import map, the vendored three.js modules"):
        status, headers, page = http("GET", f"{base}/")
        check(status == 200 and headers.get("content-type", "").startswith("text/html"),
              f"/: {status} {headers.get('content-type')}")
        found = re.search(rb'<script type="importmap">(.*?)</script>', page, re.S)
        check(found is not None, "no import map in the page")
        imports = json.loads(found.group(1))["imports"]
        manifest = get_json(f"{base}/static/vendor/three/manifest.json")
        urls = [u for u in imports.values() if not u.endswith("/")]
        urls += [f"/static/vendor/three/{f}" for f in manifest["files"]]
        urls += [m.decode() for m in re.findall(rb'<script[^>]+src="(/static/[^"]+)"', page)]
        local = root / "web" / "node_modules" / "three"
        compared = 0
        for url in dict.fromkeys(urls):
            status, headers, body = http("GET", f"{base}{url}")
            check(status == 200 and body, f"{url}: status {status}, {len(body)} bytes")
            if url.endswith(".js"):
                check("javascript" in headers.get("content-type", ""),
                      f"{url}: content-type {headers.get('content-type')!r}")
            name = url.rsplit("/", 1)[1]
            twin = {"three.module.js": local / "build" / "three.module.js",
                    "three.core.js": local / "build" / "three.core.js"}.get(name)
            if twin is not None and twin.is_file():
                check(hashlib.sha256(body).digest() == hashlib.sha256(twin.read_bytes()).digest(),
                      f"{url} differs from {twin}")
                compared += 1
        note(f"three {manifest['version']}: {len(dict.fromkeys(urls))} files served"
             + (f", {compared} identical to web/node_modules" if compared else ""))


def mapped_mkl(container: str) -> list[str]:
    """The MKL/OpenMP libraries mapped by any process of ``container`` (file names)."""
    script = ("import glob, os\nnames = set()\nfor maps in glob.glob('/proc/[0-9]*/maps'):\n"
              "    try:\n        lines = open(maps).read().splitlines()\n"
              "    except OSError:\n        continue\n"
              "    names |= {os.path.basename(l.split()[-1]) for l in lines\n"
              "              if 'libmkl' in l or 'libiomp' in l or 'libtbb' in l}\n"
              "print('\\n'.join(sorted(names)))")
    return podman("exec", container, "python", "-c", script).stdout.decode().split()


def single(image: str, root: Path) -> None:
    """One container: the API, PARDISO, GLB, web page, healthcheck."""
    name = f"{PREFIX}-api"
    cmd, env = image_cmd(image), image_env(image)
    own_port = int(env.get("FFS_PORT", "8000"))
    args = ["run", "-d", "--name", name, "--network", "host", "--read-only",
            "--tmpfs", "/tmp", "--env", f"FFS_BODY_TIMEOUT={BODY_TIMEOUT:g}"]
    if port_is_free(own_port):
        port = own_port
    else:  # another process owns the image's port on this shared host
        port = free_port()
        args += ["--env", f"FFS_PORT={port}"]
        print(f"    port {own_port} is taken on this host: FFS_PORT={port}", flush=True)
    base = f"http://127.0.0.1:{port}"
    print(f"single container, {' '.join(cmd)}:", flush=True)
    try:
        with step("container starts, GET /healthz"):
            podman(*args, image)
            health = wait_http(f"{base}/healthz", name)
            check(health == {"status": "ok"}, f"/healthz: {health}")
        with step("podman healthcheck run (the image's HEALTHCHECK)"):
            proc = podman("healthcheck", "run", name, check_rc=False)
            check(proc.returncode == 0, f"unhealthy: {proc.stdout!r} {proc.stderr!r}")
        check_header_timeout(base, float(env.get("FFS_HEADER_TIMEOUT", HEADER_TIMEOUT)))
        check_body_timeout(base, BODY_TIMEOUT)
        check_forms_and_reconstruct(base, root)
        check_web(base, root)
        with step("MKL libraries mapped in the container after the solves"):
            libs = mapped_mkl(name)
            if platform.machine() in ("x86_64", "AMD64"):
                check(any(lib.startswith("libmkl_core") for lib in libs), f"mapped: {libs}")
            note(", ".join(libs) or "none")
        with step("read-only root filesystem, non-root user"):
            proc = podman("exec", name, "sh", "-c", "id -u; touch /app/x 2>&1 || true")
            out = proc.stdout.decode().split("\n", 1)
            check(out[0].strip() != "0", f"runs as uid {out[0]}")
            check("Read-only" in out[1] or "Permission denied" in out[1], f"touch: {out[1]!r}")
            note(f"uid {out[0].strip()}; writing /app refused")
    except Exception:
        print(logs_tail(name), flush=True)
        raise
    finally:
        remove_containers([name])


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
    """``podman run`` arguments for one replica of a compose service (host network)."""
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
                   names: list[str]) -> list[str]:
    """Start scheduler, workers and API replicas; return the API base URLs."""
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


def compose(image: str, root: Path) -> None:
    """The docker-compose.yml topology from the same image, with two API replicas."""
    services = compose_services(image, root)
    print(f"compose topology (docker-compose.yml: {', '.join(services)}), host network:",
          flush=True)
    names: list[str] = []
    try:
        first, second = start_topology(image, services, 2, names)
        check_job_across_replicas(first, second, root)
        check_session_across_replicas(first, second, root)
    except Exception:
        for name in names:
            print(f"--- {name}:\n{logs_tail(name, 15)}", flush=True)
        raise
    finally:
        remove_containers(names)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=["single", "compose"])
    parser.add_argument("--image", required=True)
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    args = parser.parse_args()
    try:
        (single if args.what == "single" else compose)(args.image, args.root)
    except Exception:
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
