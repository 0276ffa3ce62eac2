"""The compose topology of scripts/docker-smoke.sh with API keys (the tools are
scripts/docker_smoke.py).

``python3 scripts/docker_smoke_compose.py --image IMAGE``
    docker-compose.yml's services (command, environment, read-only root, tmpfs,
    healthcheck, replicas) from the same image: the scheduler (waited for until healthy),
    its worker replicas and two API replicas with API keys (:func:`api_environment`); a job
    submitted through one API replica is polled and fetched through the other; a
    deformation session created through one is dragged through the other and closed. Then
    the keys (:func:`check_keys_across_replicas`, :func:`check_quota_across_replicas`,
    :func:`check_webhook`): 401 without or with an unknown key (also at the WebSocket);
    another key's job and session are 404 through the other replica (status, result,
    cancel, state, drag, the WebSocket) and served to the admin key; a key's second session
    is 429 with both header sets through the other replica and opens nothing; a job's
    webhook reaches a receiver on the host's loopback signed, retried after a 500; callback
    URLs outside FFS_WEBHOOK_HOSTS are 422; no key is in the API replicas' logs.

Standard library only (runs on the host's ``python3``). Exit status 0 when every check
passes, 1 otherwise.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import os
import socket
import sys
import threading
import time
import uuid
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from docker_smoke import (
    DEFAULT_HEADERS,
    SAMPLES,
    check,
    check_job_across_replicas,
    check_session_across_replicas,
    compose_services,
    get_json,
    http,
    logs_tail,
    note,
    podman,
    post_json,
    read_off,
    remove_containers,
    run_checks,
    start_topology,
    step,
)

KEYS = {"alice": "smoke-alice-" + uuid.uuid4().hex, "bob": "smoke-bob-" + uuid.uuid4().hex,
        "ops": "smoke-ops-" + uuid.uuid4().hex}
"""The API keys of the compose replicas (FFS_API_KEYS; ``ops`` is the admin)."""
WRONG_KEY = "smoke-wrong-" + uuid.uuid4().hex
"""A key nobody has (refused, and never written to a log either)."""
SESSIONS_PER_KEY = 1


def api_environment(receiver_port: int) -> dict[str, str]:
    """What the API replicas get on top of docker-compose.yml's environment: the keys, one
    session per key, webhooks to the receiver on the host's loopback (host network)."""
    return {"FFS_API_KEYS": json.dumps(KEYS), "FFS_ADMIN_KEYS": "ops",
            "FFS_KEY_CONCURRENT_SESSIONS": str(SESSIONS_PER_KEY),
            "FFS_WEBHOOK_HOSTS": f"127.0.0.1:{receiver_port}", "FFS_WEBHOOK_BACKOFF": "0.5"}


def bearer(name: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {KEYS[name]}"}


def as_key(name: str) -> None:
    """Send ``name``'s key with every following request of :func:`http`."""
    DEFAULT_HEADERS.update(bearer(name))


def anonymous(method: str, url: str, extra: dict[str, str]) -> tuple[int, dict[str, str],
                                                                    bytes]:
    """A request without the default key (with ``extra``'s Authorization when not empty)."""
    saved = dict(DEFAULT_HEADERS)
    DEFAULT_HEADERS.clear()
    try:
        return http(method, url, headers={k: v for k, v in extra.items() if v}, timeout=30)
    finally:
        DEFAULT_HEADERS.update(saved)


def websocket_answer(base: str, path: str, key: str) -> tuple[int, str, int | None]:
    """Open ``path``'s WebSocket offering the subprotocols ``ffs`` and ``bearer.<key>`` (as
    the page does) and read what the service says first.

    Returns:
        ``(handshake status, first text message or the refusal's body, close code)``.
    """
    parts = urlsplit(base)
    nonce = base64.b64encode(os.urandom(16)).decode()
    request = (f"GET {path} HTTP/1.1\r\nHost: {parts.netloc}\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {nonce}\r\n"
               f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: ffs, bearer.{key}\r\n\r\n")
    with socket.create_connection((parts.hostname, parts.port), timeout=60) as sock:
        sock.sendall(request.encode())
        reader = sock.makefile("rb")
        status = int(reader.readline().split()[1])
        headers = {}
        while (line := reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.decode("latin-1").partition(":")
            headers[name.strip().lower()] = value.strip()
        if status != 101:
            length = headers.get("content-length")
            return status, (reader.read(int(length)) if length else reader.read()).decode(), None
        text, code = "", None
        while code is None:
            opcode, payload = _frame(reader)
            if opcode == 1 and not text:
                text = payload.decode()
            elif opcode == 8:
                code = int.from_bytes(payload[:2], "big") if len(payload) >= 2 else 1005
        return status, text, code


def _frame(reader: Any) -> tuple[int, bytes]:
    """One (unmasked, unfragmented) frame from the server: ``(opcode, payload)``."""
    first, second = reader.read(2)
    length = second & 0x7F
    if length == 126:
        length = int.from_bytes(reader.read(2), "big")
    elif length == 127:
        length = int.from_bytes(reader.read(8), "big")
    return first & 0x0F, reader.read(length)


def check_keys_across_replicas(first: str, second: str, root: Path) -> None:
    """401 without or with a wrong key; a job and a session of alice's are 404 for bob
    through the other replica, over HTTP and the WebSocket, and served to the admin key
    there; /metrics is the admin's."""
    vertices, faces = read_off(root / SAMPLES / "torus.off")
    with step("API keys: 401 without a key, another key's job and session 404 across replicas"):
        for base in (first, second):
            for extra in ({"Authorization": f"Bearer {WRONG_KEY}"}, {"Authorization": ""}):
                status, headers, _ = anonymous("GET", f"{base}/v1/jobs", extra)
                check(status == 401 and headers.get("www-authenticate", "").startswith(
                    "Bearer"), f"{base}: {status} {headers}")
        as_key("alice")
        headers, _ = post_json(f"{first}/v1/jobs", {"operation": "forms", "input": {
            "vertices": vertices, "faces": faces}}, expect=202)
        job = headers["location"]
        while get_json(f"{first}{job}")["status"] in ("queued", "running"):
            time.sleep(0.3)
        as_key("bob")
        for method, path in (("GET", job), ("GET", f"{job}/result"), ("DELETE", job)):
            status = http(method, f"{second}{path}")[0]
            check(status == 404, f"bob: {method} {path} of alice's job via replica 2: {status}")
        status, _, _ = http("GET", f"{second}/metrics")
        check(status == 403, f"/metrics for a user key: {status}")
        as_key("ops")
        listed = [j["id"] for j in get_json(f"{second}/v1/jobs")]
        check(job.rsplit("/", 1)[1] in listed, "the admin key does not list alice's job")
        get_json(f"{second}{job}/result")
        metrics = http("GET", f"{second}/metrics")[2].decode()
        check('ffs_key_requests_total{key="bob"}' in metrics, "no per-key metrics")
        as_key("alice")
        small = {"vertices": vertices, "faces": faces, "handles": [{"vertex": 0}, {"vertex": 1}]}
        headers, _ = post_json(f"{first}/v1/sessions", small, expect=201)
        session = headers["location"]
        drag = {"handle_positions": [vertices[0], vertices[1]]}
        as_key("bob")
        status = http("GET", f"{second}{session}")[0]
        check(status == 404, f"bob reads alice's session via replica 2: {status}")
        status = http("POST", f"{second}{session}/solve", json.dumps(drag).encode(),
                      {"Content-Type": "application/json"})[0]
        check(status == 404, f"bob drags alice's session via replica 2: {status}")
        status, text, code = websocket_answer(second, f"{session}/ws", KEYS["bob"])
        check(status == 101 and json.loads(text)["status"] == 404 and code == 4404,
              f"bob's WebSocket to alice's session via replica 2: {status} {text!r} {code}")
        status, text, _ = websocket_answer(second, f"{session}/ws", WRONG_KEY)
        check(status == 401, f"a WebSocket with an unknown key: {status} {text!r}")
        as_key("ops")
        post_json(f"{second}{session}/solve", drag)
        status = http("DELETE", f"{second}{session}")[0]
        check(status == 204, f"the admin closes alice's session: {status}")
        as_key("alice")
        note(f"job {job} and session {session}: 404 for another key via replica 2 (status, "
             "result, cancel, state, drag, WebSocket close 4404), served to the admin key; "
             "401 without or with an unknown key (HTTP and WebSocket)")


def check_quota_across_replicas(first: str, second: str, root: Path) -> None:
    """A key's second session, through the other replica, is 429 with Retry-After and the
    RateLimit fields, and opens nothing."""
    vertices, faces = read_off(root / SAMPLES / "torus.off")
    doc = {"vertices": vertices, "faces": faces, "handles": [{"vertex": 0}, {"vertex": 1}]}
    with step(f"a key's sessions ({SESSIONS_PER_KEY} at once) counted across replicas: 429"):
        as_key("alice")
        headers, _ = post_json(f"{first}/v1/sessions", doc, expect=201)
        session = headers["location"]
        status, headers, body = http("POST", f"{second}/v1/sessions", json.dumps(doc).encode(),
                                     {"Content-Type": "application/json"})
        problem = json.loads(body)
        check(status == 429 and problem.get("quota") == "concurrent-sessions",
              f"a second session via replica 2: {status} {body[:300]!r}")
        check(headers.get("retry-after", "").isdigit() and headers.get(
            "ratelimit-policy", "").startswith(f'"concurrent-sessions";q={SESSIONS_PER_KEY}')
            and headers.get("ratelimit", "").startswith('"concurrent-sessions";r=0'),
            f"429 headers: {headers}")
        listed = [s["id"] for s in get_json(f"{second}/v1/sessions")]
        check(listed == [session.rsplit("/", 1)[1]], f"alice's sessions after the 429: {listed}")
        check(http("DELETE", f"{second}{session}")[0] == 204, "alice closes her session")
        note(f"429 quota-exceeded, Retry-After {headers['retry-after']}, RateLimit-Policy "
             f"{headers['ratelimit-policy']}; still one session listed")


class Receiver:
    """A webhook receiver on the host's loopback: records every request; the first POST
    to each path is answered 500, the next ones 200."""

    def __init__(self) -> None:
        self.requests: list[dict[str, Any]] = []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                first = not any(r["path"] == self.path for r in receiver.requests)
                receiver.requests.append({"path": self.path, "method": self.command,
                                          "body": body, "headers": dict(self.headers)})
                self.send_response(500 if first else 200)
                self.send_header("Content-Length", "0")
                self.end_headers()

            do_GET = do_POST  # noqa: N815 (a followed redirect would show up)

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def wait(self, path: str, count: int, timeout: float = 120) -> list[dict[str, Any]]:
        deadline = time.monotonic() + timeout
        while len(found := [r for r in self.requests if r["path"] == path]) < count:
            check(time.monotonic() < deadline, f"{path}: {len(found)} of {count} webhooks")
            time.sleep(0.2)
        return found

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def check_webhook(first: str, second: str, root: Path, receiver: Receiver) -> None:
    """A job with a callback_url: its status document POSTed to the receiver, signed with
    alice's webhook secret (HMAC-SHA256(key, "ffs-webhook")), again after a 500; callback
    URLs outside FFS_WEBHOOK_HOSTS refused with 422 naming callback_url."""
    vertices, faces = read_off(root / SAMPLES / "torus.off")
    job = {"operation": "forms", "input": {"vertices": vertices, "faces": faces}}
    with step("webhook: signed, retried after a 500; other hosts refused at submission"):
        as_key("alice")
        for url in ("http://10.0.0.1/x", f"http://127.0.0.1:{receiver.port + 1}/x"):
            status, _, body = http("POST", f"{first}/v1/jobs", json.dumps(
                {**job, "callback_url": url}).encode(), {"Content-Type": "application/json"})
            check(status == 422 and json.loads(body)["errors"][0]["field"] == "callback_url",
                  f"callback_url {url}: {status} {body[:300]!r}")
        headers, _ = post_json(f"{first}/v1/jobs", {
            **job, "callback_url": f"http://127.0.0.1:{receiver.port}/hook"}, expect=202)
        attempts = receiver.wait("/hook", 2)
        status_doc = get_json(f"{second}{headers['location']}")
        secret = hmac.new(KEYS["alice"].encode(), b"ffs-webhook", hashlib.sha256).hexdigest()
        for attempt in attempts:
            fields = dict(p.split("=", 1) for p in attempt["headers"]["X-FFS-Signature"].split(","))
            mac = hmac.new(secret.encode(), fields["t"].encode() + b"." + attempt["body"],
                           hashlib.sha256).hexdigest()
            check(hmac.compare_digest(mac, fields["v1"]), "a webhook's signature does not verify")
            check(json.loads(attempt["body"]) == status_doc, "the webhook's body is not the "
                  f"job's status document: {attempt['body'][:300]!r}")
        check([a["headers"]["X-FFS-Attempt"] for a in attempts] == ["1", "2"] and len(
            {a["headers"]["X-FFS-Delivery"] for a in attempts}) == 1, "attempts 1, 2 of one "
            "delivery expected")
        note(f"{len(attempts)} attempts (500, then 200), signatures verified, event "
             f"{attempts[-1]['headers']['X-FFS-Event']}; 10.0.0.1 and another port: 422")


def check_no_key_in_logs(containers: list[str]) -> None:
    """No key, nor the wrong one sent, in any API replica's output."""
    with step("no key in the API replicas' logs"):
        for name in (n for n in containers if "-api-" in n):
            proc = podman("logs", name, check_rc=False)  # the service writes to stderr
            log = (proc.stdout + proc.stderr).decode(errors="replace")
            check("GET /v1/jobs" in log, f"{name}'s log has no access lines: {log[-500:]!r}")
            leaked = [k for k, v in {**KEYS, "wrong": WRONG_KEY}.items() if v in log]
            check(not leaked, f"{name}'s log holds the key(s) of {leaked}")


def compose(image: str, root: Path) -> None:
    """The docker-compose.yml topology from the same image, with two API replicas and API
    keys (:func:`api_environment`)."""
    services = compose_services(image, root)
    print(f"compose topology (docker-compose.yml: {', '.join(services)}, with API keys), "
          "host network:", flush=True)
    names: list[str] = []
    receiver = Receiver()
    try:
        first, second = start_topology(image, services, 2, names,
                                       api_environment(receiver.port))
        as_key("alice")
        check_job_across_replicas(first, second, root)
        check_session_across_replicas(first, second, root)
        check_keys_across_replicas(first, second, root)
        check_quota_across_replicas(first, second, root)
        check_webhook(first, second, root, receiver)
        check_no_key_in_logs(names)
    except Exception:
        for name in names:
            print(f"--- {name}:\n{logs_tail(name, 15)}", flush=True)
        raise
    finally:
        receiver.close()
        remove_containers(names)


if __name__ == "__main__":
    sys.exit(run_checks(compose, __doc__.split("\n\n")[0]))
