"""Signed webhooks of finished jobs (issue 46) against a real uvicorn and a real receiver on
loopback: delivered with a signature that the snippet of docs/deployment.md verifies,
retried after 500s with the same delivery id, redirects never followed, and callback URLs
outside FFS_WEBHOOK_HOSTS (other hosts, other ports, private addresses) refused at
submission with a 422 naming ``callback_url``. No request leaves loopback."""

from __future__ import annotations

import itertools
import json
import re
import ssl
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import httpx
import pytest

from service.access.keys import derived_webhook_secret
from service.access.webhooks import (
    CallbackRefusedError,
    WebhookPolicy,
    WebhookSender,
    check_callback_url,
    pinned_request,
    signature,
)
from tests.helpers import REPO
from tests.helpers.aio import run as run_async
from tests.helpers.meshes import icosphere
from tests.helpers.servers import running_app, uvicorn_process
from tests.helpers.service import metric_value, problem

KEY = "webhook-key-0123456789"
ADMIN = "webhook-admin-9876543210"


class Receiver:
    """An HTTP server on 127.0.0.1 that records every request, whatever its method;
    ``plan[path]`` lists the statuses to answer in turn (then 200), a 3xx redirecting to
    ``/elsewhere``."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0,
                 tls: ssl.SSLContext | None = None) -> None:
        self.requests: list[dict[str, Any]] = []
        self.plan: dict[str, list[int]] = {}
        self.lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                with receiver.lock:
                    receiver.requests.append({"path": self.path, "body": body,
                                              "method": self.command,
                                              "headers": dict(self.headers), "at": time.time()})
                    statuses = receiver.plan.get(self.path, [])
                    status = statuses.pop(0) if statuses else 200
                self.send_response(status)
                if 300 <= status < 400:
                    self.send_header("Location", "/elsewhere")
                self.send_header("Content-Length", "0")
                self.end_headers()

            # A followed 301/302/303 arrives as a GET: recorded all the same.
            do_GET = do_PUT = do_DELETE = do_PATCH = do_POST  # noqa: N815

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer((host, port), Handler)
        if tls is not None:  # HTTPS: the handshake happens in the handler's thread
            self.server.socket = tls.wrap_socket(self.server.socket, server_side=True,
                                                 do_handshake_on_connect=False)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def at(self, path: str) -> list[dict[str, Any]]:
        with self.lock:
            return [r for r in self.requests if r["path"] == path]

    def wait(self, path: str, count: int, timeout: float = 60) -> list[dict[str, Any]]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if len(found := self.at(path)) >= count:
                return found
            time.sleep(0.05)
        raise AssertionError(f"{path}: {len(self.at(path))} of {count} requests")

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture(scope="module")
def receiver() -> Iterator[Receiver]:
    found = Receiver()
    yield found
    found.close()


@pytest.fixture(scope="module")
def server(receiver) -> Iterator[str]:
    env = {"FFS_WORKERS": "1", "FFS_API_KEYS": json.dumps({"hooks": KEY, "ops": ADMIN}),
           "FFS_ADMIN_KEYS": "ops", "FFS_WEBHOOK_HOSTS": f"127.0.0.1:{receiver.port}",
           "FFS_WEBHOOK_BACKOFF": "0.2", "FFS_WEBHOOK_ATTEMPTS": "3"}
    with uvicorn_process(env) as (base, _):
        yield base


@pytest.fixture(scope="module")
def http(server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server, timeout=60,
                      headers={"Authorization": f"Bearer {KEY}"}) as client:
        yield client


def _documented_verifier():
    """The verification snippet of docs/deployment.md, run as documented."""
    text = (REPO / "docs" / "deployment.md").read_text(encoding="utf-8")
    code = re.search(r"<!-- webhook-verification -->\n```python\n(.*?)```", text, re.S)
    assert code, "the snippet is marked in docs/deployment.md"
    namespace: dict[str, Any] = {}
    exec(compile(code.group(1), "deployment.md", "exec"), namespace)
    return namespace["verify_ffs_webhook"]


def _job(receiver: Receiver, path: str, **extra: Any) -> dict[str, Any]:
    V, F = icosphere(1)
    return {"operation": "forms", "input": {"vertices": V.tolist(), "faces": F.tolist()},
            "callback_url": f"http://127.0.0.1:{receiver.port}{path}", **extra}


def test_a_finished_job_is_delivered_signed(http, receiver):
    verify = _documented_verifier()
    submitted = http.post("/v1/jobs", json=_job(receiver, "/done"))
    assert submitted.status_code == 202, submitted.text
    [delivery] = receiver.wait("/done", 1)
    status = http.get(submitted.headers["location"]).json()
    assert json.loads(delivery["body"]) == status and status["status"] == "succeeded"
    headers = {k.lower(): v for k, v in delivery["headers"].items()}
    assert headers["x-ffs-event"] == "job.succeeded" and headers["x-ffs-attempt"] == "1"
    assert headers["content-type"] == "application/json"
    secret = derived_webhook_secret(KEY)  # a key of FFS_API_KEYS: HMAC(key, "ffs-webhook")
    assert verify(secret, headers["x-ffs-signature"], delivery["body"])
    assert not verify(secret, headers["x-ffs-signature"], delivery["body"] + b" ")
    assert not verify("another-secret", headers["x-ffs-signature"], delivery["body"])
    stale = signature(secret, int(time.time()) - 3600, delivery["body"])
    assert not verify(secret, stale, delivery["body"])  # replayed an hour later
    assert KEY not in delivery["body"].decode() and KEY not in str(headers)


def test_cancelled_and_failed_jobs_are_delivered_too(http, receiver):
    from tests.helpers.service import forms_json

    slow = {"operation": "reconstruct", "callback_url": f"http://127.0.0.1:{receiver.port}/end",
            "input": {**forms_json(*icosphere(5)), "options": {"exact_shortcut": False}}}
    submitted = http.post("/v1/jobs", json=slow)
    assert submitted.status_code == 202, submitted.text
    assert http.delete(submitted.headers["location"]).status_code == 200
    bad = _job(receiver, "/end")
    bad["input"]["faces"] = (icosphere(1)[1] + 1000).tolist()  # index out of range: the job fails
    assert http.post("/v1/jobs", json=bad).status_code == 202
    deliveries = receiver.wait("/end", 2)
    events = sorted(d["headers"]["X-FFS-Event"] for d in deliveries)
    assert events == ["job.cancelled", "job.failed"], events
    failed = next(json.loads(d["body"]) for d in deliveries
                  if d["headers"]["X-FFS-Event"] == "job.failed")
    assert failed["status"] == "failed" and failed["error"]["kind"] == "index-out-of-range"


def test_a_failing_receiver_is_retried_with_backoff(http, receiver, server):
    receiver.plan["/flaky"] = [500, 503]
    submitted = http.post("/v1/jobs", json=_job(receiver, "/flaky"))
    assert submitted.status_code == 202, submitted.text
    attempts = receiver.wait("/flaky", 3)
    time.sleep(0.5)
    assert len(receiver.at("/flaky")) == 3  # the third answered 200: no more
    headers = [{k.lower(): v for k, v in a["headers"].items()} for a in attempts]
    assert [h["x-ffs-attempt"] for h in headers] == ["1", "2", "3"]
    assert len({h["x-ffs-delivery"] for h in headers}) == 1
    gaps = [b["at"] - a["at"] for a, b in itertools.pairwise(attempts)]
    assert gaps[0] >= 0.2 and gaps[1] >= 0.4  # FFS_WEBHOOK_BACKOFF, doubled


def _deliveries(server: str) -> dict[str, float]:
    with httpx.Client(base_url=server, headers={"Authorization": f"Bearer {ADMIN}"}) as ops:
        text = ops.get("/metrics").text
    return {outcome: metric_value(text, "ffs_webhook_deliveries_total", outcome=outcome)
            for outcome in ("delivered", "retried", "given-up")}


@pytest.mark.parametrize("status", [302, 307])
def test_redirects_are_not_followed_and_attempts_are_bounded(http, receiver, server, status):
    """A receiver that redirects (302: a follower would GET the new place, 307: POST it
    again) is tried again at the same URL, never at the one it names, and given up after
    FFS_WEBHOOK_ATTEMPTS."""
    before = _deliveries(server)
    path = f"/moved-{status}"
    receiver.plan[path] = [status] * 10
    submitted = http.post("/v1/jobs", json=_job(receiver, path))
    assert submitted.status_code == 202, submitted.text
    attempts = receiver.wait(path, 3)
    time.sleep(1.5)
    assert len(receiver.at(path)) == 3  # FFS_WEBHOOK_ATTEMPTS
    assert {a["method"] for a in attempts} == {"POST"}
    assert receiver.at("/elsewhere") == []
    after = _deliveries(server)
    assert after["given-up"] - before["given-up"] == 1
    assert after["retried"] - before["retried"] == 2
    assert after["delivered"] == before["delivered"]


@pytest.mark.parametrize("url", [
    "http://127.0.0.2:{port}/x",          # loopback, not listed
    "http://127.0.0.1:{other}/x",         # the listed host on another port
    "http://localhost:{port}/x",          # a name for it, not listed
    "http://10.0.0.1/x", "http://169.254.169.254/latest/meta-data",  # private, metadata
    "http://example.com/x", "ftp://127.0.0.1:{port}/x", "/relative",
    "http://user:pw@127.0.0.1:{port}/x",
])
def test_callbacks_outside_the_allowed_hosts_are_refused_at_submission(http, receiver, url):
    before = len(http.get("/v1/jobs").json())
    body = _job(receiver, "/never")
    body["callback_url"] = url.format(port=receiver.port, other=receiver.port + 1)
    doc = problem(http.post("/v1/jobs", json=body), 422, "validation-error")
    assert doc["errors"][0]["field"] == "callback_url" and "callback_url" in doc["detail"]
    assert len(http.get("/v1/jobs").json()) == before  # no job was created
    V, F = icosphere(1)  # the form field of an upload too
    from solver.mesh.io import save_mesh

    upload = http.post("/v1/jobs", data={"operation": "forms", "callback_url": body[
        "callback_url"]}, files={"file": ("m.off", save_mesh(V, F, "off"))})
    assert problem(upload, 422, "validation-error")["errors"][0]["field"] == "callback_url"
    assert receiver.at("/never") == []


def test_the_policy_alone():
    policy = WebhookPolicy(("hooks.example.com", "*.corp.example", "10.1.2.3"))
    assert check_callback_url("https://hooks.example.com/a", policy).exact
    assert not check_callback_url("https://x.corp.example/a", policy).exact
    assert check_callback_url("http://10.1.2.3:80/a", policy).exact  # listed exactly
    for url in ("https://corp.example.evil.com/", "http://10.1.2.4/", "https://example.com",
                "https://hooks.example.com.evil/", "javascript:alert(1)"):
        with pytest.raises(CallbackRefusedError):
            check_callback_url(url, policy)
    with pytest.raises(CallbackRefusedError, match="FFS_WEBHOOK_HOSTS is empty"):
        check_callback_url("https://hooks.example.com/", WebhookPolicy())
    assert WebhookPolicy(attempts=4, backoff=0.5).delays() == [0.5, 1.0, 2.0]


@pytest.mark.parametrize("entry", ["[::1]:8080", "[::1]", "::1", "0:0::1", "[0:0:0::1]:8080"])
def test_an_ipv6_host_is_named_as_in_a_url_or_bare(entry):
    """An IPv6 loopback listed as a URL writes it (``[::1]:8080``) or bare, in any spelling,
    allows a callback to it (exactly: a special address); another port or address does not."""
    policy = WebhookPolicy((entry,))
    assert check_callback_url("http://[::1]:8080/hook", policy).exact
    for url in ("http://[::2]:8080/hook", "http://127.0.0.1:8080/hook"):
        with pytest.raises(CallbackRefusedError):
            check_callback_url(url, policy)
    if "]:" in entry:
        with pytest.raises(CallbackRefusedError):
            check_callback_url("http://[::1]:9090/hook", policy)


class Rebinding:
    """``socket.getaddrinfo`` for one name answering ``answers[0]`` the first time it is
    asked, ``answers[1]`` every later time (a DNS rebinding); any other host is resolved for
    real. ``asked`` counts the questions about the name."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, name: str, answers: list[str]) -> None:
        import socket

        self.asked = 0
        real = socket.getaddrinfo

        def getaddrinfo(host: Any, port: Any, *args: Any, **kwargs: Any) -> Any:
            if host != name:
                return real(host, port, *args, **kwargs)
            address = answers[min(self.asked, 1)]
            self.asked += 1
            family = socket.AF_INET6 if ":" in address else socket.AF_INET
            where = (address, int(port), 0, 0) if ":" in address else (address, int(port))
            return [(family, socket.SOCK_STREAM, 6, "", where)]

        monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)


@pytest.mark.parametrize("address", ["127.0.0.1", "10.0.0.1", "169.254.169.254",
                                     "100.100.100.200", "100.64.0.1", "0.0.0.0", "224.0.0.1",
                                     "::1", "fd00::1", "::ffff:127.0.0.1", "64:ff9b::a00:1"])
def test_a_wildcard_host_never_reaches_a_non_global_address(address, monkeypatch):
    """What a ``*.`` entry's name resolves to at delivery: any address that is not globally
    reachable is refused, the shared address space 100.64.0.0/10 (not ``is_private``; a
    cloud's metadata service may live there) included; a global one is what the request is
    sent to."""
    target = check_callback_url("https://a.corp.example/hook", WebhookPolicy(("*.corp.example",)))
    Rebinding(monkeypatch, "a.corp.example", [address, address])
    with pytest.raises(CallbackRefusedError, match="resolves to a loopback or private"):
        run_async(pinned_request(target))
    Rebinding(monkeypatch, "a.corp.example", ["93.184.215.14", "93.184.215.14"])
    assert str(run_async(pinned_request(target)).url) == "https://93.184.215.14/hook"


@pytest.mark.parametrize(("first", "then"), [("93.184.215.14", "127.0.0.1"),
                                              ("2606:2800:21f:cb07:6820:80da:af6b:8b2c", "::1"),
                                              ("127.0.0.1", "93.184.215.14")])
def test_a_wildcard_name_is_resolved_once_and_the_request_goes_to_that_address(
        first, then, monkeypatch):
    """DNS rebinding: a name that answers a public address to the check and a private one
    afterwards. The delivery's request names the address checked (the ``Host`` header and
    TLS's SNI the name), so the HTTP client has nothing to resolve; a first answer that is
    private is refused, whatever comes next."""
    name = "hooks.corp.example"
    target = check_callback_url(f"https://{name}:8443/a?b=1",
                                WebhookPolicy(("*.corp.example",)))
    rebinding = Rebinding(monkeypatch, name, [first, then])
    if first == "127.0.0.1":
        with pytest.raises(CallbackRefusedError):
            run_async(pinned_request(target))
        assert rebinding.asked == 1
        return
    pinned = run_async(pinned_request(target))
    assert rebinding.asked == 1
    assert pinned.url.host == first and pinned.url.port == 8443
    assert pinned.url.path == "/a" and pinned.url.query == b"b=1"
    assert pinned.headers == {"Host": f"{name}:8443"}
    assert pinned.extensions == {"sni_hostname": name}


def test_the_http_client_connects_to_the_resolved_address_not_the_name(monkeypatch):
    """A real delivery to two receivers on loopback, one port, 127.0.0.1 and 127.0.0.2: the
    name resolves to the first once, to the second whenever asked again. The webhook arrives
    at the first, with the name in ``Host``, and the name was asked once per attempt: the
    HTTP client never resolved it again. (A name listed exactly: a ``*.`` entry refuses
    loopback, and this machine has no public address to listen on.)"""
    first = Receiver("127.0.0.1")
    second = Receiver("127.0.0.2", first.port)
    try:
        name = "hooks.rebind.example"
        target = check_callback_url(f"http://{name}:{first.port}/pinned",
                                    WebhookPolicy((f"{name}:{first.port}",)))
        rebinding = Rebinding(monkeypatch, name, ["127.0.0.1", "127.0.0.2"])
        sender = WebhookSender(WebhookPolicy(attempts=1, timeout=10))

        async def deliver() -> bool:
            try:
                return await sender.deliver(target, "s3cret", "job.succeeded", b"{}", "j")
            finally:
                await sender.stop()

        assert run_async(deliver())
        [delivery] = first.at("/pinned")
        assert delivery["headers"]["Host"] == f"{name}:{first.port}"
        assert second.requests == [] and rebinding.asked == 1
    finally:
        first.close()
        second.close()


def _certificates(folder: Any, names: list[str]) -> tuple[str, dict[str, tuple[str, str]]]:
    """A test CA (its PEM path) and, per name, a certificate for that DNS name signed by it
    (cert and key PEM paths)."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.UTC)
    pem = serialization.Encoding.PEM

    def issue(subject: str, key: Any, issuer: Any, issuer_key: Any, ca: bool) -> Any:
        builder = (x509.CertificateBuilder()
                   .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
                   .issuer_name(issuer).public_key(key.public_key())
                   .serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(hours=1))
                   .not_valid_after(now + datetime.timedelta(hours=1))
                   .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
        if not ca:
            builder = builder.add_extension(
                x509.SubjectAlternativeName([x509.DNSName(subject)]), critical=False)
        else:
            builder = builder.add_extension(x509.KeyUsage(
                digital_signature=True, key_cert_sign=True, crl_sign=True,
                content_commitment=False, key_encipherment=False, data_encipherment=False,
                key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        return builder.sign(issuer_key, hashes.SHA256())

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ffs test CA")])
    ca = issue("ffs test CA", ca_key, ca_name, ca_key, ca=True)
    (folder / "ca.pem").write_bytes(ca.public_bytes(pem))
    leaves = {}
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        (folder / f"{name}.pem").write_bytes(
            issue(name, key, ca_name, ca_key, ca=False).public_bytes(pem))
        (folder / f"{name}.key").write_bytes(key.private_bytes(
            pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))
        leaves[name] = (str(folder / f"{name}.pem"), str(folder / f"{name}.key"))
    return str(folder / "ca.pem"), leaves


@pytest.mark.parametrize("served", ["hooks.rebind.example", "elsewhere.example"])
def test_a_pinned_https_delivery_keeps_the_name_for_tls(served, monkeypatch, tmp_path):
    """HTTPS to the pinned address: the receiver (on 127.0.0.1) is asked for the name by SNI
    and its certificate is checked against the name, not the address: a certificate for the
    name is accepted, one for another name refused (the delivery is not sent)."""
    name = "hooks.rebind.example"
    ca, leaves = _certificates(tmp_path, [served])
    tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    tls.load_cert_chain(*leaves[served])
    asked: list[str | None] = []
    tls.sni_callback = lambda sock, server_name, context: asked.append(server_name)
    receiver = Receiver("127.0.0.1", tls=tls)
    try:
        target = check_callback_url(f"https://{name}:{receiver.port}/tls",
                                    WebhookPolicy((f"{name}:{receiver.port}",)))
        Rebinding(monkeypatch, name, ["127.0.0.1", "127.0.0.2"])
        sender = WebhookSender(WebhookPolicy(attempts=1, timeout=10))
        sender._client = httpx.AsyncClient(  # the sender's client, trusting the test CA
            verify=ssl.create_default_context(cafile=ca), follow_redirects=False,
            trust_env=False, timeout=10, limits=httpx.Limits(max_keepalive_connections=0))

        async def deliver() -> bool:
            try:
                return await sender.deliver(target, "s3cret", "job.succeeded", b"{}", "j")
            finally:
                await sender.stop()

        delivered = run_async(deliver())
        assert asked and set(asked) == {name}
        if served == name:
            assert delivered
            [delivery] = receiver.at("/tls")
            assert delivery["headers"]["Host"] == f"{name}:{receiver.port}"
        else:
            assert not delivered and receiver.at("/tls") == []
    finally:
        receiver.close()


def test_without_keys_a_callback_is_refused():
    with running_app(workers=1, webhook_hosts=["127.0.0.1"]) as client:
        V, F = icosphere(1)
        response = client.post("/v1/jobs", json={
            "operation": "forms", "input": {"vertices": V.tolist(), "faces": F.tolist()},
            "callback_url": "http://127.0.0.1/x"})
        doc = problem(response, 422, "validation-error")
        assert doc["errors"][0]["field"] == "callback_url" and "API keys" in doc["detail"]
