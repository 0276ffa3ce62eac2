"""Fixtures of the browser tests: a real uvicorn on loopback (:mod:`tests.helpers.servers`), a
headless Debian Chromium driven by Python Playwright, and a page whose console errors fail
the test.

Chromium is the distribution's (``/usr/bin/chromium``; ``scripts/test.sh`` installs the
``chromium`` package when it runs as root): Playwright's own browser download is never used
(no ``playwright install``). WebGL runs on SwiftShader (``--use-angle=swiftshader``). The page's
three.js modules must be built (``npm ci --prefix web``, also in ``scripts/test.sh``).
Screenshots go to ``tests/artifacts/web/`` (git-ignored).
"""

from __future__ import annotations

import json
import re
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.helpers.servers import uvicorn_server
from tests.helpers.web import (
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
    with uvicorn_server({"FFS_MAX_SESSIONS": "16", "FFS_MAX_CLIENT_SESSIONS": "16"}) as base:
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
    console: deque[str] = field(default_factory=lambda: deque(maxlen=20))
    allowed: list[re.Pattern[str]] = field(default_factory=list)

    def allow(self, pattern: str) -> None:
        self.allowed.append(re.compile(pattern))

    def unexpected(self) -> list[str]:
        return [e for e in self.errors if not any(p.search(e) for p in self.allowed)]

    def open(self, query: str = "", timeout: float = 90.0) -> Any:
        """Load the page for tests (``test`` in its query installs ``window.app``) and wait
        until its start-up work (the default sample) is done."""
        query = f"?test&{query.removeprefix('?')}" if query else "?test"
        self.page.goto(f"{self.base}/{query}", timeout=timeout * 1000)
        self.wait_for("window.app !== undefined", timeout=timeout,
                      what="the page's script to define window.app")
        self.evaluate("window.app.ready", timeout=timeout, what="window.app.ready")
        self.idle()
        return self.page

    def load_file(self, path: Any, timeout: float = 120.0) -> None:
        """Open the mesh file at ``path`` through the Mesh panel's file input and wait until
        the page shows it (its name) and has no work left."""
        name = Path(path).name
        self.page.set_input_files("#mesh-file", str(path))
        self.wait_for(f"window.app.state.name === {json.dumps(name)}", timeout=timeout,
                      what=f"{name} to be shown")
        self.idle(timeout)

    def idle(self, timeout: float = 120.0) -> None:
        """Wait until the page has no tracked work left; fail (not hang) after ``timeout``."""
        self.evaluate("window.app.idle()", timeout=timeout, what="window.app.idle()")

    def evaluate(self, expression: str, arg: Any = None, *, timeout: float = 60.0,
                 what: str = "") -> Any:
        """``page.evaluate(expression, arg)``, its promise awaited for at most ``timeout``
        seconds: then an AssertionError with the page's state (never a hang).

        ``expression`` is an expression or a function of ``arg``; it is placed in the
        evaluated function's text (no ``eval`` in the page, which its CSP forbids).
        """
        outcome = self.page.evaluate(
            f"async ([arg, ms]) => {{ const value = ({expression});"
            " const result = typeof value === 'function' ? value(arg) : value;"
            " let timer; const late = new Promise((r) => {"
            " timer = setTimeout(() => r({ late: true }), ms); });"
            " try { return await Promise.race("
            "[Promise.resolve(result).then((v) => ({ value: v })), late]); }"
            " finally { clearTimeout(timer); } }", [arg, int(timeout * 1000)])
        if outcome.get("late"):
            raise AssertionError(f"waited {timeout:g} s for {what or expression[:200]}: "
                                 f"{self.diagnostics()}")
        return outcome.get("value")

    def wait_for(self, expression: str, arg: Any = None, *, timeout: float = 30.0,
                 what: str = "") -> None:
        """Wait until ``expression`` (or the function of ``arg`` it evaluates to) is truthy,
        polled every 50 ms in the page; fail with the page's state after ``timeout``.

        Not ``page.wait_for_function``: its polls ``eval`` the expression in the page, which
        the page's CSP (no 'unsafe-eval') refuses.
        """
        self.evaluate(
            f"(arg) => new Promise((resolve, reject) => {{ const poll = () => {{ try {{"
            f" let value = ({expression}); if (typeof value === 'function') value = value(arg);"
            " if (value) resolve(true); else setTimeout(poll, 50); }"
            " catch (err) { reject(err); } }; poll(); })",
            arg, timeout=timeout, what=what or expression[:200])

    def diagnostics(self) -> str:
        """The page's state (window.app.diagnostics(): start-up, tracked work, worker calls
        in flight, progress, errors shown), its console errors and last console lines;
        bounded itself (5 s) in case the page does not answer."""
        try:
            state = self.page.wait_for_function(
                "() => ({ url: location.href, app: !window.app ? 'window.app is not defined'"
                " : window.app.diagnostics ? window.app.diagnostics()"
                " : { mesh: window.app.state.name, errors: window.app.state.errors } })",
                timeout=5000, polling=100).json_value()
        except Exception as exc:  # a page that does not answer is a diagnosis too
            state = f"the page did not answer ({type(exc).__name__}: {exc})"
        return (f"page state: {state}; console errors: {self.errors}; "
                f"last console lines: {list(self.console)}")

    def app(self, expression: str, arg: Any = None, timeout: float = 120.0) -> Any:
        """Evaluate ``expression`` (a function of ``app`` and ``arg``) and await it."""
        return self.evaluate(f"async (arg) => {{ const app = window.app; "
                             f"return await ({expression}); }}", arg, timeout=timeout,
                             what=expression[:200])

    def shown_errors(self) -> list[dict[str, Any]]:
        return self.page.evaluate("window.app.state.errors")

    def frame(self) -> None:
        """Wait until the page has rendered a frame after a change."""
        self.evaluate("new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))",
                      timeout=30, what="two animation frames")

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


def _on_console(wrapper: WebPage, message: Any) -> None:
    wrapper.console.append(f"{message.type}: {message.text}")
    if message.type == "error":
        wrapper.errors.append(f"console.error: {message.text} "
                              f"({message.location.get('url', '')})")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    """A browser test that failed (a Playwright timeout included) reports the page's state."""
    outcome = yield
    report = outcome.get_result()
    web = getattr(item, "funcargs", {}).get("web")
    if report.when == "call" and report.failed and isinstance(web, WebPage):
        report.sections.append(("page state", web.diagnostics()))


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
    # A progressive drag's refined shape is long-polled; a newer drag supersedes it (409) or
    # the session closes under it (404): the browser logs those answers, the page expects them.
    wrapper.allow(r"status of (404|409) .*/drags/\d+/refined\?wait=\d+\)$")
    page.on("console", lambda m: _on_console(wrapper, m))
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
