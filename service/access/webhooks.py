"""Signed webhooks for finished jobs (docs/deployment.md#webhooks).

A job submitted with ``callback_url`` gets one POST of its status document (the body of
``GET /v1/jobs/{id}``) when it succeeds, fails or is cancelled:

* only to hosts of ``FFS_WEBHOOK_HOSTS`` (:func:`check_callback_url`, at submission: a URL
  elsewhere is refused with 422 naming ``callback_url``). A loopback, private, link-local or
  otherwise special address is refused unless the list names that host exactly; a
  ``*.example.com`` entry never reaches such an address: at delivery the name is resolved
  once, every answer checked, and the connection made to the checked address itself
  (:func:`pinned_request`: the ``Host`` header and TLS keep the name), so a name that
  answers differently when asked again cannot turn the service into a proxy into its own
  network;
* signed: ``X-FFS-Signature: t=<unix seconds>,v1=<hex HMAC-SHA256 of "<t>.<body>" under the
  key's webhook secret>`` (:func:`signature`), with ``X-FFS-Event`` (``job.succeeded``,
  ``job.failed``, ``job.cancelled``), ``X-FFS-Delivery`` (one id for every attempt) and
  ``X-FFS-Attempt``;
* retried: a connection error, a timeout, a 3xx (redirects are never followed), a 408, 429
  or 5xx is tried again after ``FFS_WEBHOOK_BACKOFF`` seconds, doubled each time, at most
  ``FFS_WEBHOOK_ATTEMPTS`` attempts in all; another 4xx ends the delivery.

The replica that accepted the job delivers its webhook (it follows the job through the
backend's contract, so jobs on a Dask cluster are covered); a webhook whose replica stops
before the job finishes is not sent.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import ipaddress
import logging
import socket
import time
import uuid
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

import httpx

logger = logging.getLogger("service.webhooks")

SIGNATURE_HEADER = "X-FFS-Signature"
RETRIED_STATUSES = frozenset({408, 429})
DEFAULT_PORTS = {"http": 80, "https": 443}


@dataclass(frozen=True)
class WebhookPolicy:
    """Where and how webhooks are delivered (FFS_WEBHOOK_*)."""

    hosts: tuple[str, ...] = ()
    attempts: int = 5
    backoff: float = 1.0
    timeout: float = 10.0
    poll_interval: float = 0.2
    """Seconds between two looks at an unfinished job (up to 1 s as it runs longer)."""

    def delays(self) -> list[float]:
        """The waits before the second, third, ... attempt."""
        return [self.backoff * 2**n for n in range(self.attempts - 1)]


class CallbackRefusedError(ValueError):
    """A callback URL the policy does not allow (the message says why)."""


def _special(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """Loopback, private, link-local, multicast, reserved, unspecified, or otherwise not
    globally reachable (``is_global``: also the shared address space 100.64.0.0/10, which
    ``is_private`` leaves out and where some clouds serve instance metadata)."""
    return (not address.is_global or address.is_loopback or address.is_private
            or address.is_link_local or address.is_multicast or address.is_reserved
            or address.is_unspecified)


def _ip(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(host)
    except ValueError:
        return None


@dataclass(frozen=True)
class CallbackTarget:
    """A checked callback URL: its host and port, and whether an exact entry of the list
    named it (then its addresses are the operator's choice)."""

    url: str
    host: str
    port: int
    exact: bool


def _names(entry: str, host: str, port: int) -> bool:
    """Whether an ``FFS_WEBHOOK_HOSTS`` entry names ``host`` (any port) or ``host:port``
    exactly; an IPv6 address as written in a URL (``[::1]``, ``[::1]:8080``) or bare, in
    any of its spellings (``0:0::1`` is ``::1``)."""
    entry = entry.strip().lower()
    name, _, entry_port = (entry[1:].partition("]") if entry.startswith("[")
                           else entry.rpartition(":") if entry.count(":") == 1
                           else (entry, "", ""))
    name = name.rstrip(".")
    entry_port = entry_port.lstrip(":")
    if entry_port and entry_port != str(port):
        return False
    if name == host:
        return True
    ours, theirs = _ip(host), _ip(name)
    return ours is not None and ours == theirs


def check_callback_url(url: str, policy: WebhookPolicy) -> CallbackTarget:
    """The target of a callback URL, if the policy allows it.

    Raises:
        CallbackRefused: not http(s), credentials in it, a host not listed, or a special
            address not listed exactly.
    """
    parts = urlsplit(url.strip())
    if parts.scheme not in DEFAULT_PORTS or not parts.hostname:
        raise CallbackRefusedError("an absolute http:// or https:// URL is required")
    if parts.username is not None or parts.password is not None:
        raise CallbackRefusedError("credentials in the URL are not allowed")
    try:
        port = parts.port or DEFAULT_PORTS[parts.scheme]
    except ValueError:
        raise CallbackRefusedError("the port is not a number in 1-65535") from None
    host = parts.hostname.lower().rstrip(".")
    if not policy.hosts:
        raise CallbackRefusedError("this service sends no webhooks (FFS_WEBHOOK_HOSTS is empty)")
    exact = any(_names(entry, host, port) for entry in policy.hosts)
    wildcard = any(entry.startswith("*.") and host.endswith(entry[1:].lower())
                   for entry in policy.hosts)
    if not exact and not wildcard:
        raise CallbackRefusedError(f"the host {host!r} is not one of FFS_WEBHOOK_HOSTS")
    address = _ip(host)
    if address is not None and _special(address) and not exact:
        raise CallbackRefusedError(f"{host} is a loopback or private address (allowed only when "
                              "FFS_WEBHOOK_HOSTS names it)")
    return CallbackTarget(url.strip(), host, port, exact)


def signature(secret: str, timestamp: int, body: bytes) -> str:
    """The ``X-FFS-Signature`` value of ``body`` sent at ``timestamp``."""
    mac = hmac.new(secret.encode("utf-8"), f"{timestamp}.".encode() + body, hashlib.sha256)
    return f"t={timestamp},v1={mac.hexdigest()}"


async def _resolved(host: str, port: int
                    ) -> list[ipaddress.IPv4Address | ipaddress.IPv6Address]:
    """The addresses of ``host`` (itself when it is one), in the resolver's order.

    Raises:
        OSError: the name does not resolve.
    """
    if (literal := _ip(host)) is not None:
        return [literal]
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    return [ipaddress.ip_address(info[4][0].split("%")[0]) for info in infos]


@dataclass(frozen=True)
class PinnedRequest:
    """A delivery's request pinned to one checked address: the URL names the address, the
    ``Host`` header and TLS (SNI, certificate check) the target's name, so the HTTP client
    connects where the check looked and resolves nothing itself."""

    url: httpx.URL
    headers: dict[str, str]
    extensions: dict[str, str]


async def pinned_request(target: CallbackTarget) -> PinnedRequest:
    """Resolve ``target``'s host once and pin the delivery to its first address.

    Raises:
        CallbackRefusedError: a ``*.`` target (not listed exactly) whose name resolves to
            a loopback, private or otherwise special address (any of its answers).
        OSError: the name does not resolve (the attempt is retried).
    """
    url = httpx.URL(target.url)
    addresses = await _resolved(target.host, target.port)
    if not addresses:
        raise OSError(f"{target.host} has no address")
    if not target.exact and any(_special(address) for address in addresses):
        raise CallbackRefusedError(f"{target.host} resolves to a loopback or private address")
    if _ip(target.host) is not None:
        return PinnedRequest(url, {}, {})
    default = DEFAULT_PORTS[url.scheme] == target.port
    host = target.host if default else f"{target.host}:{target.port}"
    return PinnedRequest(url.copy_with(host=str(addresses[0])), {"Host": host},
                         {"sni_hostname": target.host})


JobLookup = Callable[[], Awaitable[tuple[str, bytes] | None]]
"""Returns ``(status, status document)`` of a finished job, ``None`` while it runs; raises
when the job is gone."""
Outcome = Callable[[str], None]
"""Called with ``delivered``, ``retried`` or ``given-up`` (the metrics)."""


class WebhookSender:
    """Follows jobs with a callback and delivers their webhooks (module docstring)."""

    def __init__(self, policy: WebhookPolicy, on_outcome: Outcome | None = None) -> None:
        self.policy = policy
        self.on_outcome = on_outcome or (lambda outcome: None)
        self._tasks: set[asyncio.Task[None]] = set()
        self._client: httpx.AsyncClient | None = None

    def _http(self) -> httpx.AsyncClient:
        if self._client is None:
            # No keep-alive: a pooled connection is keyed by the pinned address alone and
            # could carry another name's delivery over a TLS session checked for this one.
            self._client = httpx.AsyncClient(
                follow_redirects=False, trust_env=False, timeout=self.policy.timeout,
                limits=httpx.Limits(max_keepalive_connections=0))
        return self._client

    def schedule(self, job_id: str, target: CallbackTarget, secret: str,
                 lookup: JobLookup) -> None:
        """Deliver job ``job_id``'s webhook to ``target`` once ``lookup`` says it finished."""
        task = asyncio.create_task(self._follow(job_id, target, secret, lookup))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def stop(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self._client is not None:
            await self._client.aclose()
            self._client = None

    async def _follow(self, job_id: str, target: CallbackTarget, secret: str,
                      lookup: JobLookup) -> None:
        interval = self.policy.poll_interval
        try:
            while (finished := await lookup()) is None:
                await asyncio.sleep(interval)
                interval = min(1.0, interval * 1.5)
        except Exception as exc:
            logger.warning("webhook of job %s not sent: the job is gone (%s)", job_id,
                           type(exc).__name__)
            return
        status, body = finished
        await self.deliver(target, secret, f"job.{status}", body, job_id)

    async def deliver(self, target: CallbackTarget, secret: str, event: str, body: bytes,
                      job_id: str) -> bool:
        """POST ``body`` to ``target``, retrying as the module docstring says."""
        delivery = uuid.uuid4().hex
        delays: Sequence[float] = self.policy.delays()
        for attempt in range(1, self.policy.attempts + 1):
            outcome = await self._attempt(target, secret, event, body, delivery, attempt)
            if outcome == "delivered":
                self.on_outcome("delivered")
                return True
            if outcome == "final" or attempt == self.policy.attempts:
                break
            self.on_outcome("retried")
            await asyncio.sleep(delays[attempt - 1])
        self.on_outcome("given-up")
        logger.warning("webhook of job %s given up after %d attempt(s) (%s)", job_id,
                       attempt, target.host)
        return False

    async def _attempt(self, target: CallbackTarget, secret: str, event: str, body: bytes,
                       delivery: str, attempt: int) -> str:
        """``delivered``, ``retry`` or ``final`` (a 4xx other than 408/429, or a refused
        address)."""
        try:
            pinned = await pinned_request(target)
        except CallbackRefusedError as exc:
            logger.warning("webhook to %s refused: %s", target.host, exc)
            return "final"
        except OSError as exc:
            logger.info("webhook attempt %d to %s: the name does not resolve (%s)", attempt,
                        target.host, type(exc).__name__)
            return "retry"
        headers = {"Content-Type": "application/json", "User-Agent": "ffs-webhooks/1",
                   SIGNATURE_HEADER: signature(secret, int(time.time()), body),
                   "X-FFS-Event": event, "X-FFS-Delivery": delivery,
                   "X-FFS-Attempt": str(attempt), **pinned.headers}
        try:
            response = await self._http().post(pinned.url, content=body, headers=headers,
                                               extensions=pinned.extensions)
        except httpx.HTTPError as exc:
            logger.info("webhook attempt %d to %s failed: %s", attempt, target.host,
                        type(exc).__name__)
            return "retry"
        if 200 <= response.status_code < 300:
            return "delivered"
        logger.info("webhook attempt %d to %s answered %d", attempt, target.host,
                    response.status_code)
        if 300 <= response.status_code < 400 or response.status_code >= 500 \
                or response.status_code in RETRIED_STATUSES:
            return "retry"
        return "final"
