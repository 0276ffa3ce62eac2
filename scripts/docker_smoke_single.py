"""Container checks of scripts/docker-smoke.sh: one container of the built image with its
own CMD and HEALTHCHECK (the tools and the compose topology are scripts/docker_smoke.py).

``python3 scripts/docker_smoke_single.py --image IMAGE``: FFS_PORT moved when 8000 is taken;
FFS_BODY_TIMEOUT=5: ``/healthz``; a client trickling its request head is answered 408 and cut
off after FFS_HEADER_TIMEOUT, one trickling its body after a complete head gets the 408
``body-timeout`` problem after FFS_BODY_TIMEOUT; ``/v1/forms`` of a mesh file against edge
lengths computed here; exact forms reconstructed (lengths match the file's); perturbed,
non-integrable forms reconstructed by least squares with the PARDISO backend; a GLB that the
Khronos validator (tools/gltf-validator) accepts; the web page, every module of its import
map and every vendored three.js file; the MKL libraries the solver process has mapped.

Standard library only (runs on the host's ``python3``). Exit status 0 when every check
passes, 1 otherwise.
"""

from __future__ import annotations

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
from pathlib import Path
from typing import Any

from docker_smoke import (
    PREFIX,
    SAMPLES,
    check,
    expected_backend,
    free_port,
    get_json,
    http,
    lengths_of,
    logs_tail,
    max_relative_gap,
    note,
    podman,
    port_is_free,
    post_form,
    post_json,
    read_off,
    remove_containers,
    run_checks,
    step,
    unique_edges,
    wait_http,
)

HEADER_TIMEOUT = 10.0
"""FFS_HEADER_TIMEOUT's default (service/settings.py), unless the image sets it."""
BODY_TIMEOUT = 5.0
"""FFS_BODY_TIMEOUT of the single container (its default, 60 s, would make the check last a
minute; the value only sets how long the trickled body is waited for)."""


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
    /healthz.

    Args:
        base: The API's base URL.
        first: The bytes sent at once.
        limit: Seconds to trickle at most.

    Returns:
        ``(what the server answered, bytes trickled, seconds until it closed or None)``.
    """
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


if __name__ == "__main__":
    sys.exit(run_checks(single, __doc__.split("\n\n")[0]))
