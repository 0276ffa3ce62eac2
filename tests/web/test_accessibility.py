"""axe-core (tools/axe-core, from its committed lockfile) on the web page, tab by tab, in
Chromium: no violation of serious or critical impact (issue 43: color-contrast on three
elements), and a level-one heading.

axe is injected into a page whose context bypasses the page's Content-Security-Policy
(the policy refuses every script that is not the page's own, which is what it is for)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.helpers import REPO
from tests.helpers.web import VIEWPORT
from tests.web.conftest import WebPage

AXE = REPO / "tools" / "axe-core" / "node_modules" / "axe-core" / "axe.min.js"
TABS = ("mesh", "deform", "flatten", "forms")
BLOCKING = ("serious", "critical")


@pytest.fixture
def checked(browser: Any, web_server: str) -> Iterator[WebPage]:
    if not AXE.is_file():
        pytest.fail("axe-core is not installed: npm ci --prefix tools/axe-core "
                    "(scripts/test.sh does)")
    context = browser.new_context(viewport=VIEWPORT, bypass_csp=True)
    page = context.new_page()
    wrapper = WebPage(page, web_server)
    try:
        yield wrapper
    finally:
        page.goto("about:blank")  # pagehide: the page deletes its session
        context.close()


def _violations(web: WebPage) -> list[dict[str, Any]]:
    web.page.add_script_tag(content=AXE.read_text(encoding="utf-8"))
    return web.page.evaluate("""async () => {
        const result = await axe.run(document, { resultTypes: ['violations'] });
        return result.violations.map((v) => ({ id: v.id, impact: v.impact, help: v.help,
            nodes: v.nodes.map((n) => n.target.join(' ') + ': ' + n.failureSummary) }));
    }""")


@pytest.mark.parametrize("tab", TABS)
def test_no_serious_violation_on_each_tab(checked: WebPage, tab: str) -> None:
    page = checked.open()
    page.click(f"#tab-{tab}")
    if tab == "deform":  # the handle list and its buttons, as a user has them
        checked.app("app.makeHandle([0, 1, 2])")
        checked.app("app.makeHandle(app.visibleVertices().slice(600, 606))")
    if tab == "flatten":  # the layout beside the view, its figures
        page.click("#flatten")
        checked.wait_for("window.app.state.flat !== null", timeout=180)
        checked.idle()
    if tab == "forms":
        page.click("#bend-forms")
        checked.wait_for("window.app.state.source === 'reconstruction'", timeout=180)
        checked.idle()
    checked.frame()
    found = _violations(checked)
    blocking = [v for v in found if v["impact"] in BLOCKING]
    assert not blocking, blocking


def test_page_has_a_level_one_heading(checked: WebPage) -> None:
    page = checked.open()
    assert page.locator("h1").count() == 1
    assert page.locator("h1").inner_text().strip() == "Fundamental forms"
