"""API keys: who a caller is, its role and its limits.

Two sources, both off by default:

* ``FFS_API_KEYS_FILE``: a JSON file ``{"keys": [{"name", "role", "hash", "limits"?,
  "webhook_secret"}]}`` holding only each key's SHA-256 (:func:`hash_key`); ``python -m
  service.access add NAME`` creates a key, prints it once and appends its hash
  (:mod:`service.access.__main__`).
* ``FFS_API_KEYS``: a JSON object name -> key for one-line deployments and tests, every key
  with the role ``user`` unless ``FFS_ADMIN_KEYS`` names it, and the default limits.

A presented key is hashed and compared with every stored hash by
:func:`hmac.compare_digest` (constant time, and no early exit on the first match), so
neither the time of a lookup nor its result says how much of a key was right. Keys are
random 256-bit tokens, so a plain SHA-256 is enough to store them (a slow password hash
protects guessable secrets, which these are not).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

Role = Literal["user", "admin"]
ROLES: tuple[Role, ...] = ("user", "admin")
KEY_PREFIX = "ffs_"
"""Every generated key starts with this (so that secret scanners can spot one)."""
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
"""A key's name: it labels metrics and owns jobs and sessions, so it is kept plain."""


@dataclass(frozen=True)
class KeyLimits:
    """The quotas of one key (``None``: the service-wide default of that quota).

    Attributes:
        requests_per_minute: Requests in any 60 s window (429 beyond).
        concurrent_jobs: Jobs queued or running at once (429 beyond).
        concurrent_sessions: Deformation sessions open at once (429 beyond).
        max_faces: Faces of one mesh in a request (413 beyond).
    """

    requests_per_minute: int | None = None
    concurrent_jobs: int | None = None
    concurrent_sessions: int | None = None
    max_faces: int | None = None

    def __post_init__(self) -> None:
        """Refuse a limit that is not a whole number of at least 1 (a 0 would otherwise
        read as unset and give the key the service-wide default)."""
        for name, value in asdict(self).items():
            if value is not None and (type(value) is not int or value < 1):
                raise ValueError(f"the limit {name} must be a whole number of at least 1 "
                                 f"(or absent: the default), not {value!r}")

    def over(self, defaults: KeyLimits) -> KeyLimits:
        """These limits, each unset one taken from ``defaults``."""
        return KeyLimits(**{name: value if value is not None else getattr(defaults, name)
                            for name, value in asdict(self).items()})


@dataclass(frozen=True)
class ApiKey:
    """One key as the service knows it: never the key itself, only its hash.

    Attributes:
        name: Who it is (metrics labels, ownership of jobs and sessions, logs).
        role: ``user`` or ``admin`` (``/metrics``, every job and session).
        digest: :func:`hash_key` of the key.
        limits: Its quotas.
        webhook_secret: The HMAC secret of its jobs' webhooks.
    """

    name: str
    role: Role
    digest: str = field(repr=False)
    limits: KeyLimits = KeyLimits()
    webhook_secret: str = field(default="", repr=False)

    @property
    def is_admin(self) -> bool:
        return self.role == "admin"


def hash_key(key: str) -> str:
    """The stored form of a key: ``sha256:`` and its hex digest."""
    return "sha256:" + hashlib.sha256(key.encode("utf-8")).hexdigest()


def new_key() -> str:
    """A fresh key: :data:`KEY_PREFIX` and 256 random bits, URL-safe (also a valid
    WebSocket subprotocol token)."""
    return KEY_PREFIX + secrets.token_urlsafe(32)


def derived_webhook_secret(key: str) -> str:
    """The webhook secret of a key given in ``FFS_API_KEYS``: HMAC-SHA256 of
    ``ffs-webhook`` under the key, hex (its holder can compute it, nobody else)."""
    return hmac.new(key.encode("utf-8"), b"ffs-webhook", hashlib.sha256).hexdigest()


class KeyRing:
    """The known keys; :meth:`authenticate` finds a presented one in constant time."""

    def __init__(self, keys: Iterable[ApiKey] = (), required: bool = False) -> None:
        self._keys = tuple(keys)
        self._required = required or bool(self._keys)
        names = [k.name for k in self._keys]
        if len(set(names)) != len(names):
            raise ValueError("two API keys have the same name")

    @property
    def enabled(self) -> bool:
        """Whether keys are required: any key is configured, or a keys file is named (even
        an empty one: then nobody gets in). Else the service is open, as by default."""
        return self._required

    def __len__(self) -> int:
        return len(self._keys)

    def names(self) -> list[str]:
        return [k.name for k in self._keys]

    def authenticate(self, presented: str | None) -> ApiKey | None:
        """The key ``presented`` is, or None (unknown, empty or missing).

        Every stored hash is compared (:func:`hmac.compare_digest`), whatever matched.
        """
        if not presented:
            return None
        digest = hash_key(presented).encode()
        found = None
        for key in self._keys:
            if hmac.compare_digest(digest, key.digest.encode()):
                found = key
        return found


def ring_from_mapping(keys: Mapping[str, str], admins: Iterable[str],
                      defaults: KeyLimits) -> list[ApiKey]:
    """The keys of ``FFS_API_KEYS`` (name -> key), those named in ``FFS_ADMIN_KEYS`` admin.

    Raises:
        ValueError: an admin name that is not a key, or an empty key.
    """
    admins = set(admins)
    unknown = admins - set(keys)
    if unknown:
        raise ValueError(f"FFS_ADMIN_KEYS names no key of FFS_API_KEYS: {sorted(unknown)}")
    out = []
    for name, key in keys.items():
        if not key:
            raise ValueError(f"FFS_API_KEYS: the key of {name!r} is empty")
        out.append(ApiKey(name, "admin" if name in admins else "user", hash_key(key),
                          defaults, derived_webhook_secret(key)))
    return out


def ring_from_file(path: Path, defaults: KeyLimits, admins: Iterable[str] = ()
                   ) -> list[ApiKey]:
    """The keys of an ``FFS_API_KEYS_FILE`` (see the module docstring).

    Raises:
        ValueError: the file is missing (a mistyped path must not open the service) or is
            not such a document (naming the entry).
    """
    if not path.is_file():
        raise ValueError(f"FFS_API_KEYS_FILE {path} does not exist (create it with python "
                         "-m service.access add NAME --file ...)")
    document = read_keys_file(path)
    admins = set(admins)
    out = []
    for index, entry in enumerate(document.get("keys", [])):
        try:
            limits = KeyLimits(**(entry.get("limits") or {})).over(defaults)
            role = "admin" if entry["name"] in admins else entry.get("role", "user")
            if role not in ROLES:
                raise ValueError(f"role {role!r} is not one of {ROLES}")
            out.append(ApiKey(str(entry["name"]), role, str(entry["hash"]), limits,
                              str(entry.get("webhook_secret", ""))))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: keys[{index}]: {exc}") from None
    return out


def read_keys_file(path: Path) -> dict[str, Any]:
    """The document of a keys file (``{"keys": []}`` when it does not exist).

    Raises:
        ValueError: not JSON, or not ``{"keys": [...]}``.
    """
    if not path.exists():
        return {"keys": []}
    try:
        document = json.loads(path.read_text(encoding="utf-8") or "{}")
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not JSON: {exc}") from None
    if not isinstance(document, dict) or not isinstance(document.get("keys", []), list):
        raise ValueError(f'{path}: expected {{"keys": [...]}}')
    return document


def add_key(path: Path, name: str, role: Role = "user", limits: KeyLimits = KeyLimits()
            ) -> tuple[str, str]:
    """Create a key named ``name`` in the file at ``path`` (created if missing, written
    atomically, mode 0600).

    Returns:
        ``(key, webhook secret)``: shown once; the file keeps the key's hash only.

    Raises:
        ValueError: the name is taken or invalid, or the role unknown.
    """
    import re

    if not re.match(NAME_PATTERN, name):
        raise ValueError(f"the name {name!r} must match {NAME_PATTERN}")
    if role not in ROLES:
        raise ValueError(f"role {role!r} is not one of {ROLES}")
    document = read_keys_file(path)
    if any(entry.get("name") == name for entry in document["keys"]):
        raise ValueError(f"{path} already has a key named {name!r}")
    key, secret = new_key(), secrets.token_hex(32)
    entry: dict[str, Any] = {"name": name, "role": role, "hash": hash_key(key),
                             "webhook_secret": secret}
    chosen = {k: v for k, v in asdict(limits).items() if v is not None}
    if chosen:
        entry["limits"] = chosen
    document["keys"].append(entry)
    _write_private(path, json.dumps(document, indent=2) + "\n")
    return key, secret


def _write_private(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            out.write(text)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
