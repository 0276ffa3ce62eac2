"""The page on a service with API keys (issue 46), in Debian's Chromium against a real
uvicorn: the first 401 asks for a key (a wrong one asks again), the key is kept for the tab
only (sessionStorage: a new tab asks again, nothing in localStorage or cookies), the mesh
opens through the worker, a deformation runs over the session's WebSocket with the key in a
subprotocol (not in the URL), and the server's log holds no key."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest

from tests.helpers.servers import server_log, uvicorn_process
from tests.web.conftest import VENDOR_MANIFEST, VIEWPORT, WebPage, _on_console

KEY = "page-key-0123456789abcdef"


@pytest.fixture(scope="module")
def keyed_server() -> Iterator[str]:
    if not VENDOR_MANIFEST.is_file():
        pytest.fail("the page's three.js modules are not built: run `npm ci --prefix web`")
    env = {"FFS_API_KEYS": json.dumps({"viewer": KEY}), "FFS_MAX_SESSIONS": "16"}
    with uvicorn_process(env, log_level="info") as (base, _):
        yield base


@pytest.fixture
def keyed_page(browser: Any, keyed_server: str) -> Iterator[tuple[Any, WebPage]]:
    context = browser.new_context(viewport=VIEWPORT)
    page = context.new_page()
    page.set_default_timeout(60_000)
    wrapper = WebPage(page, keyed_server)
    wrapper.allow(r"status of 401")  # the browser logs the 401s the page answers with a prompt
    page.on("console", lambda m: _on_console(wrapper, m))
    page.on("pageerror", lambda e: wrapper.errors.append(f"page error: {e}"))
    try:
        yield context, wrapper
    finally:
        page.goto("about:blank")
        context.close()
    assert not wrapper.unexpected(), wrapper.unexpected()


def _answer(page: Any, key: str, web: WebPage | None = None) -> str:
    """Wait for the key dialog, type ``key`` and submit; returns the dialog's text (with
    ``web``, a screenshot of it first: tests/artifacts/web/api-key-dialog-*.png)."""
    dialog = page.locator("#api-key-dialog[open]")
    dialog.wait_for(timeout=60_000)
    text = dialog.inner_text()
    if web is not None:
        web.screenshot("api-key-dialog")
    page.fill("#api-key-input", key)
    page.click("#api-key-use")
    return text


def test_the_page_asks_for_a_key_and_keeps_it_for_the_tab(keyed_page, keyed_server):
    context, web = keyed_page
    page = web.page
    page.goto(f"{keyed_server}/?test", timeout=90_000)
    first = _answer(page, "not-the-key", web)
    assert "needs an API key" in first
    again = _answer(page, KEY)  # the wrong key was refused: asked again, saying so
    assert "does not know this key" in again
    web.evaluate("window.app.ready", timeout=120, what="the page's start-up")
    web.idle()
    assert web.app("app.state.name") and web.shown_errors() == []
    assert page.evaluate("sessionStorage.getItem('ffs.apiKey')") == KEY
    assert page.evaluate("Object.values(localStorage).join()") == ""
    assert context.cookies() == []
    web.app("app.setRefine(false)")
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle([600])")
    web.app("app.dragHandle(0, 0, 6)")
    assert "WebSocket" in web.app("app.state.transport.label")
    assert web.shown_errors() == []
    # Another tab of the same browser has no key yet: it asks.
    other = context.new_page()
    other.on("console", lambda m: _on_console(web, m))
    other.goto(f"{keyed_server}/?test", timeout=90_000)
    _answer(other, KEY)
    other.evaluate("window.app.ready")
    other.goto("about:blank")
    other.close()
    page.goto("about:blank")  # the page closes its session
    log = server_log(keyed_server).read_text()
    assert '"GET /v1/me HTTP/1.1" 200' in log  # the access log is on (API calls logged)
    assert KEY not in log and "not-the-key" not in log


def test_swagger_ui_authorize_sends_the_key(browser: Any, keyed_server: str) -> None:
    """/docs: the document's bearer scheme gives Swagger UI its Authorize button; a request
    tried out after authorizing carries the key (GET /v1/me names it), before it a 401."""
    context = browser.new_context(viewport=VIEWPORT)
    page = context.new_page()
    try:
        page.goto(f"{keyed_server}/docs")
        page.wait_for_selector(".opblock-summary", timeout=60_000)
        operation = page.locator("#operations-health-get_caller")  # GET /v1/me

        def try_me() -> str:
            if not operation.locator(".execute").count():
                if not operation.locator(".try-out__btn").count():
                    operation.locator(".opblock-summary").click()
                operation.locator(".try-out__btn").click()
            operation.locator(".execute").click()
            status = operation.locator(".live-responses-table tbody .response-col_status").first
            status.wait_for(timeout=30_000)
            return status.inner_text().strip()

        assert try_me().startswith("401")
        page.click("button.authorize")
        page.locator(".auth-container input").first.fill(KEY)
        page.locator(".auth-btn-wrapper button.authorize").first.click()
        page.locator(".auth-btn-wrapper button.btn-done, button.close-modal").first.click()
        operation.locator(".btn-clear").first.click()
        assert try_me().startswith("200")
        assert '"viewer"' in operation.locator(".live-responses-table").inner_text()
    finally:
        context.close()
