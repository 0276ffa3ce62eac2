"""What a newcomer hits (issue 43), in a real browser against a real uvicorn: the page
survives reloads that revalidate its cached scripts (the 304 answers carry the same security
headers as the 200s), every HTML page's Content-Security-Policy names no external source."""

from __future__ import annotations

import re

import httpx
import pytest

CACHED_HEADERS = ("content-security-policy", "x-content-type-options", "x-frame-options",
                  "cache-control")
"""The headers Chromium merges from a 304 into its cached copy: they must match the 200's."""


@pytest.mark.parametrize("path", ["/static/js/worker.js", "/static/js/main.js",
                                  "/static/style.css", "/static/samples/index.json",
                                  "/static/index.html"])
def test_revalidation_keeps_the_headers(web_server: str, path: str) -> None:
    with httpx.Client(base_url=web_server, timeout=10) as http:
        fresh = http.get(path)
        assert fresh.status_code == 200
        again = http.get(path, headers={"If-None-Match": fresh.headers["etag"]})
        assert again.status_code == 304
        for name in CACHED_HEADERS:
            assert again.headers.get(name) == fresh.headers.get(name), name


def _loaded(web) -> None:
    web.wait_for("window.app !== undefined", timeout=90, what="window.app")
    web.evaluate("window.app.ready", timeout=90, what="window.app.ready")
    web.idle()
    assert web.page.evaluate("window.app.state.name"), web.diagnostics()
    assert web.shown_errors() == []


def test_page_works_after_reloads(web) -> None:
    web.open()
    statuses: dict[str, list[int]] = {}
    web.page.on("response", lambda r: statuses.setdefault(
        r.url.split("?")[0].removeprefix(web.base), []).append(r.status))
    for _ in range(2):  # the second reload finds the worker's script cached and revalidated
        web.page.reload()
        _loaded(web)
        faces = web.app("app.state.faces ? app.state.faces.length / 3 : 0")
        assert faces > 0
    assert 304 in statuses.get("/static/js/worker.js", []) + statuses.get(
        "/static/js/main.js", []), statuses  # the reloads did revalidate


EXTERNAL = re.compile(r"https?://|//[a-z0-9.-]+\.[a-z]{2,}|\*")


@pytest.mark.parametrize("path", ["/", "/docs", "/redoc", "/static/index.html"])
def test_policy_names_no_external_source(web_server: str, path: str) -> None:
    with httpx.Client(base_url=web_server, timeout=10) as http:
        policy = http.get(path).headers["content-security-policy"]
    assert not EXTERNAL.search(policy), policy
    assert "'unsafe-eval'" not in policy and "script-src 'self'" in policy


def test_redoc_asks_for_no_external_logo(browser, web_server: str) -> None:
    context = browser.new_context()
    page = context.new_page()
    outside: list[str] = []
    problems: list[str] = []
    page.on("request", lambda r: "127.0.0.1" not in r.url and not r.url.startswith(
        ("data:", "blob:")) and outside.append(r.url))
    page.on("console", lambda m: m.type == "error" and problems.append(m.text))
    try:
        page.goto(f"{web_server}/redoc")
        page.wait_for_selector("h1", timeout=60_000)
        page.wait_for_timeout(1000)
        content = page.content()
    finally:
        context.close()
    assert outside == [] and problems == [], (outside, problems)
    assert "cdn.redoc.ly" not in content
