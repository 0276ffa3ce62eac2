"""Fixtures of the browser tests: a real uvicorn on loopback (:mod:`helpers.servers`), a
headless Debian Chromium driven by Python Playwright, and a page whose console errors fail
the test.

Chromium is the distribution's (``/usr/bin/chromium``; ``scripts/test.sh`` installs the
``chromium`` package when it runs as root): Playwright's own browser download is never used
(no ``playwright install``). WebGL runs on SwiftShader (``--use-angle=swiftshader``). The page's
three.js modules must be built (``npm ci --prefix web``, also in ``scripts/test.sh``).
Screenshots go to ``tests/artifacts/web/`` (git-ignored).
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import httpx
import pytest
from helpers.servers import uvicorn_server
from web_helpers import (
    ARTIFACTS,
    CHROMIUM_ARGS,
    SMALL_VIEWPORT,
    VENDOR_MANIFEST,
    VIEWPORT,
    chromium_path,
)


@pytest.fixture(scope="session")
def web_server() -> Iterator[str]:
    """Base URL of a real uvicorn serving the page and the API."""
    if not VENDOR_MANIFEST.is_file():
        pytest.fail("the page's three.js modules are not built: run `npm ci --prefix web` "
                    "(scripts/test.sh does)")
    with uvicorn_server({"FFS_MAX_SESSIONS": "16"}) as base:
        yield base


@pytest.fixture(scope="session")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium_path(),
                                             args=CHROMIUM_ARGS, timeout=60_000)
        try:
            yield browser
        finally:
            browser.close()


@dataclass
class WebPage:
    """A page plus what its console said; ``allow`` whitelists expected console errors."""

    page: Any
    base: str
    errors: list[str] = field(default_factory=list)
    allowed: list[re.Pattern[str]] = field(default_factory=list)

    def allow(self, pattern: str) -> None:
        self.allowed.append(re.compile(pattern))

    def unexpected(self) -> list[str]:
        return [e for e in self.errors if not any(p.search(e) for p in self.allowed)]

    def open(self, query: str = "") -> Any:
        """Load the page and wait until its start-up work (the default sample) is done."""
        self.page.goto(f"{self.base}/{query}")
        self.page.wait_for_function("window.app !== undefined")
        self.page.evaluate("window.app.ready")
        self.idle()
        return self.page

    def idle(self, timeout: float = 120.0) -> None:
        """Wait until the page has no tracked work left; fail (not hang) after ``timeout``."""
        done = self.page.evaluate(
            "(ms) => Promise.race([window.app.idle().then(() => true),"
            " new Promise((r) => setTimeout(() => r(false), ms))])", int(timeout * 1000))
        if not done:
            state = self.page.evaluate(
                "({name: window.app.state.name, errors: window.app.state.errors,"
                " progress: document.querySelector('#progress')?.textContent})")
            raise AssertionError(f"the page was still busy after {timeout:g} s: {state}")

    def app(self, expression: str, arg: Any = None) -> Any:
        """Evaluate ``expression`` (a function of ``app`` and ``arg``) and await it."""
        return self.page.evaluate(f"async ([arg]) => {{ const app = window.app; "
                                  f"return await ({expression}); }}", [arg])

    def shown_errors(self) -> list[dict[str, Any]]:
        return self.page.evaluate("window.app.state.errors")

    def frame(self) -> None:
        """Wait until the page has rendered a frame after a change."""
        self.page.evaluate(
            "new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")

    def screenshot(self, name: str) -> bytes:
        """Save ``name``-1400x900.png and ``name``-1280x720.png; returns the large one."""
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        self.frame()
        png = self.page.screenshot(path=str(ARTIFACTS / f"{name}-1400x900.png"))
        self.page.set_viewport_size(SMALL_VIEWPORT)
        self.frame()
        self.page.screenshot(path=str(ARTIFACTS / f"{name}-1280x720.png"))
        self.page.set_viewport_size(VIEWPORT)
        self.frame()
        return png


def _session_count(base: str) -> int | None:
    text = httpx.get(f"{base}/metrics", timeout=10).text
    match = re.search(r"^ffs_sessions (\d+(?:\.\d+)?)$", text, re.MULTILINE)
    return None if match is None else int(float(match.group(1)))


@pytest.fixture
def web(browser: Any, web_server: str) -> Iterator[WebPage]:
    """A fresh page (own context) that fails the test on console errors or page errors, and
    on a deformation session it leaves open when it goes away."""
    context = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
    page = context.new_page()
    page.set_default_timeout(30_000)
    wrapper = WebPage(page, web_server)
    page.on("console", lambda m: m.type == "error" and wrapper.errors.append(
        f"console.error: {m.text} ({m.location.get('url', '')})"))
    page.on("pageerror", lambda e: wrapper.errors.append(f"page error: {e}"))
    try:
        yield wrapper
    finally:
        try:
            shown = page.evaluate("window.app ? window.app.state.errors : []")
        except Exception:  # the page may be gone already
            shown = []
        page.goto("about:blank")  # pagehide: the page deletes its session
        context.close()
    unexpected = wrapper.unexpected()
    assert not unexpected, f"console errors: {unexpected}; errors shown on the page: {shown}"
    deadline = time.monotonic() + 10
    while (count := _session_count(web_server)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not count, f"{count} deformation session(s) left open by the page"
