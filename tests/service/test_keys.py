"""The key store and quotas alone (issue 46): hashing, lookup, the keys file and its command,
FFS_API_KEYS / FFS_ADMIN_KEYS parsing (never echoing a key), the request-rate window and its
IETF header fields."""

from __future__ import annotations

import json

import pytest

from service.access.__main__ import main as access_main
from service.access.keys import (
    KeyLimits,
    KeyRing,
    add_key,
    hash_key,
    ring_from_file,
    ring_from_mapping,
)
from service.access.quotas import CONCURRENT_JOBS, RateLimiter
from service.http.auth import key_ring
from service.settings import Settings

DEFAULTS = KeyLimits(600, 16, 4, 1000)


def test_a_key_is_found_by_its_hash_only():
    ring = KeyRing(ring_from_mapping({"alice": "k-alice", "ops": "k-ops"}, ["ops"], DEFAULTS))
    assert ring.authenticate("k-alice").name == "alice"
    assert ring.authenticate("k-ops").is_admin
    for wrong in ("k-alic", "k-alice ", "", None, hash_key("k-alice")):
        assert ring.authenticate(wrong) is None
    assert "k-alice" not in repr(ring.authenticate("k-alice"))  # no digest or secret either
    with pytest.raises(ValueError, match="same name"):
        KeyRing([*ring_from_mapping({"a": "1"}, [], DEFAULTS),
                 *ring_from_mapping({"a": "2"}, [], DEFAULTS)])
    with pytest.raises(ValueError, match="names no key"):
        ring_from_mapping({"a": "1"}, ["b"], DEFAULTS)


def test_the_keys_file_and_its_command(tmp_path, capsys):
    path = tmp_path / "keys.json"
    assert access_main(["add", "ci", "--file", str(path), "--max-faces", "50",
                        "--role", "admin"]) == 0
    printed = capsys.readouterr().out
    key = next(line for line in printed.splitlines() if line.startswith("ffs_"))
    assert key not in path.read_text() and hash_key(key) in path.read_text()
    [found] = ring_from_file(path, DEFAULTS)
    assert (found.name, found.role, found.limits) == ("ci", "admin", KeyLimits(600, 16, 4, 50))
    assert found.webhook_secret in printed
    assert access_main(["add", "ci", "--file", str(path)]) == 1  # the name is taken
    assert "already has a key named 'ci'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="must match"):
        add_key(path, "bad name")
    path.write_text(json.dumps({"keys": [{"name": "x", "role": "root", "hash": "h"}]}))
    with pytest.raises(ValueError, match=r"keys\[0\]: role 'root'"):
        ring_from_file(path, DEFAULTS)
    assert access_main(["list", "--file", str(path)]) == 0
    assert capsys.readouterr().out.startswith("x root {}")
    path.write_text("{not json")
    assert access_main(["list", "--file", str(path)]) == 1  # a reason, not a traceback
    assert "is not JSON" in capsys.readouterr().err


@pytest.mark.parametrize("value", [0, -1, "5", 2.5, True])
def test_a_limit_below_one_or_not_whole_is_refused(tmp_path, capsys, value):
    """Not read as unset (a 0 used to give the key the service's default quota)."""
    path = tmp_path / "keys.json"
    path.write_text(json.dumps({"keys": [{"name": "x", "hash": "h",
                                          "limits": {"concurrent_jobs": value}}]}))
    with pytest.raises(ValueError, match=r"keys\[0\]: the limit concurrent_jobs must be"):
        ring_from_file(path, DEFAULTS)
    if isinstance(value, int) and not isinstance(value, bool):
        assert access_main(["add", "y", "--file", str(tmp_path / "new.json"),
                            "--concurrent-jobs", str(value)]) == 1
        assert "the limit concurrent_jobs must be" in capsys.readouterr().err
        assert not (tmp_path / "new.json").exists()


def test_settings_read_keys_without_echoing_them(monkeypatch, tmp_path):
    monkeypatch.setenv("FFS_API_KEYS", '{"alice": "secret-one", "ops": "secret-two"}')
    monkeypatch.setenv("FFS_ADMIN_KEYS", "ops")
    settings = Settings()
    assert "secret-one" not in repr(settings) and "secret-one" not in str(settings.api_keys)
    ring = key_ring(settings)
    assert ring.names() == ["alice", "ops"] and ring.authenticate("secret-two").is_admin
    for broken in ('{"alice": "secret-one",', '["secret-one"]', '{"alice": ["secret-one"]}'):
        monkeypatch.setenv("FFS_API_KEYS", broken)
        with pytest.raises(ValueError) as refused:
            key_ring(Settings())
        assert "secret-one" not in str(refused.value) and "FFS_API_KEYS" in str(refused.value)
    monkeypatch.delenv("FFS_API_KEYS")
    monkeypatch.delenv("FFS_ADMIN_KEYS")
    assert not key_ring(Settings()).enabled  # no keys: off
    assert key_ring(Settings(api_keys={"bob": "k"})).names() == ["bob"]
    with pytest.raises(ValueError, match="does not exist"):  # a mistyped path: no open door
        key_ring(Settings(api_keys_file=tmp_path / "typo.json"))
    (tmp_path / "empty.json").write_text('{"keys": []}')
    assert key_ring(Settings(api_keys_file=tmp_path / "empty.json")).enabled  # nobody gets in


def test_the_request_window_and_its_headers():
    now = [100.0]
    limiter = RateLimiter(clock=lambda: now[0])
    decisions = [limiter.take("a", 2) for _ in range(3)]
    assert [d.allowed for d in decisions] == [True, True, False]
    assert decisions[0].headers() == {"RateLimit-Policy": '"requests";q=2;w=60',
                                      "RateLimit": '"requests";r=1;t=60'}
    now[0] = 130.2
    refused = limiter.take("a", 2)
    assert refused.headers()["Retry-After"] == "30" and refused.headers()["RateLimit"] == \
        '"requests";r=0;t=30'
    assert limiter.take("b", 2).allowed  # per key
    now[0] = 160.0
    assert limiter.take("a", 2).allowed  # a new window
    assert CONCURRENT_JOBS.headers(3, 0, 5) == {
        "RateLimit-Policy": '"concurrent-jobs";q=3;qu="concurrent-requests"',
        "RateLimit": '"concurrent-jobs";r=0;t=5'}
