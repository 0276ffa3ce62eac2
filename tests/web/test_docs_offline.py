"""/docs (Swagger UI) and /redoc (ReDoc) render with the network blocked: their files come
from this service (``npm ci --prefix web`` copies them from web/package-lock.json), never from
a CDN. Every request that does not go to loopback is aborted and recorded."""

from __future__ import annotations

import json
from typing import Any
from urllib.parse import urlsplit

import pytest

from tests.helpers import REPO

LOOPBACK = {"127.0.0.1", "localhost", "::1", "[::1]"}
DOCUMENT = json.loads((REPO / "openapi" / "openapi.json").read_text(encoding="utf-8"))
SUMMARIES = [op["summary"] for item in DOCUMENT["paths"].values() for op in item.values()]


@pytest.fixture
def offline(browser: Any) -> Any:
    """A page whose non-loopback requests are aborted; ``page.blocked`` lists them and
    ``page.problems`` its console errors and page errors."""
    context = browser.new_context()
    blocked: list[str] = []
    problems: list[str] = []

    def route(route: Any) -> None:
        if urlsplit(route.request.url).hostname in LOOPBACK:
            route.continue_()
        else:
            blocked.append(route.request.url)
            route.abort("internetdisconnected")

    context.route("**/*", route)
    page = context.new_page()
    page.on("console", lambda m: m.type == "error" and problems.append(m.text))
    page.on("pageerror", lambda e: problems.append(str(e)))
    page.blocked, page.problems = blocked, problems
    try:
        yield page
    finally:
        context.close()


def test_swagger_ui_renders_offline(offline: Any, web_server: str) -> None:
    response = offline.goto(f"{web_server}/docs")
    assert response.status == 200
    offline.wait_for_selector(".opblock-summary", timeout=60_000)
    assert "Fundamental forms service" in offline.inner_text(".info .title")
    shown = offline.locator(".opblock-summary-description").all_inner_texts()
    assert set(SUMMARIES) <= set(shown), set(SUMMARIES) - set(shown)
    offline.locator(".opblock-summary", has_text="/v1/jobs/{job_id}/mesh").first.click()
    offline.wait_for_selector(".opblock-body .responses-table", timeout=30_000)
    assert "model/gltf-binary" in offline.inner_text(".opblock-body")
    assert offline.blocked == [] and offline.problems == [], (offline.blocked,
                                                               offline.problems)


def test_redoc_renders_offline(offline: Any, web_server: str) -> None:
    response = offline.goto(f"{web_server}/redoc")
    assert response.status == 200
    offline.wait_for_selector("h1", timeout=60_000)
    offline.wait_for_function("document.body.innerText.includes('Submit a job')",
                              timeout=60_000)
    text = offline.inner_text("body")
    assert "Fundamental forms service" in text
    missing = [s for s in SUMMARIES if s not in text]
    assert not missing, missing
    # ReDoc's sidebar logo comes from this service too (web/build.mjs rewrites its URL).
    assert offline.blocked == [] and offline.problems == [], (offline.blocked,
                                                               offline.problems)
