"""The page's tabs, declared once (index.html's tab list): each number key and each click
selects its tab and shows its panel only, and the help overlay names every tab and the keys
that reach them, read from that list. Chromium via Playwright, on the real service."""

from __future__ import annotations

TAB_BUTTONS = """Array.from(document.querySelectorAll('[role="tab"]')).map((b) => ({
  name: b.id.slice(4), label: b.firstChild.textContent.trim(),
  panel: b.getAttribute("aria-controls") }))"""


def shown(page) -> list[str]:
    return page.evaluate("""Array.from(document.querySelectorAll('[role="tabpanel"]'))
        .filter((p) => !p.hidden).map((p) => p.id)""")


def test_keys_clicks_and_help_follow_the_one_tab_list(web):
    page = web.open("sample=decimated-knight.off")
    tabs = page.evaluate(TAB_BUTTONS)
    assert [t["name"] for t in tabs][:2] == ["mesh", "deform"] and len(tabs) >= 5
    for number, tab in enumerate(tabs, start=1):  # keys 1..N in the list's order
        assert tab["panel"] == f"panel-{tab['name']}"
        page.keyboard.press(str(number))
        assert shown(page) == [tab["panel"]]
        assert page.get_attribute(f"#tab-{tab['name']}", "aria-selected") == "true"
        assert web.app("app.state.tab") == tab["name"]
    page.keyboard.press(str(len(tabs) + 1))  # past the last tab: nothing changes
    assert shown(page) == [tabs[-1]["panel"]]
    for tab in reversed(tabs):  # clicks
        page.click(f"#tab-{tab['name']}")
        assert shown(page) == [tab["panel"]]
        selected = [t["name"] for t in tabs
                    if page.get_attribute(f"#tab-{t['name']}", "aria-selected") == "true"]
        assert selected == [tab["name"]]
    page.click("#help-open")
    keys = page.locator("#help-tab-keys").inner_text()
    names = page.locator("#help-tabs").inner_text()
    assert keys == f"1\u2013{len(tabs)}"  # an en dash
    assert names == ", ".join(t["label"] for t in tabs) + " tab"
    page.click("#help-close")
