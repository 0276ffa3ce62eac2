"""The page as a new user meets it, in a real browser against a real uvicorn: the first view
(upright, plain colours for exact forms, a verdict in words), the layout at 1400x900 and
1280x720 (tabs: the main actions never need scrolling), view helpers, undo/redo, the help
overlay, and the bugs of issue 12, each with a test that fails without its fix: a stale
report after a refused mesh and during slow loads, the distortion legend after "Reset shape",
toasts that repeat and never close, a progress bar that moves the layout, numbers broken
across lines, Flatten offered on closed meshes, jargon shown to users.
"""

from __future__ import annotations

import re

import httpx
import numpy as np
import pytest

from tests.helpers.web import (
    ARTIFACTS,
    SMALL_VIEWPORT,
    VIEWPORT,
    assert_not_blank,
    rigid_align,
    worker_wrapper,
)

REPO_DATA = ARTIFACTS.parents[1] / "data"

# Delays the page's requests to URLs containing a pattern, from the page and from its worker
# (a slow server, as the browser sees it; the page's code is untouched): the worker is started
# through a wrapper module that patches its fetch() (tests.helpers.web.worker_wrapper, the page's
# worker module statically imported: no message can arrive before it listens).
# window.__setSlow(pattern, ms).
SLOW_PATCH = """
  const slow = { pattern: null, ms: 0 };
  new BroadcastChannel("slow").onmessage = (e) => Object.assign(slow, e.data);
  const fastFetch = self.fetch.bind(self);
  self.fetch = async (input, init) => {
    const url = typeof input === "string" ? input : input.url;
    if (slow.pattern && url.includes(slow.pattern)) {
      await new Promise((r) => setTimeout(r, slow.ms));
    }
    return fastFetch(input, init);
  };"""
SLOW_FETCH = worker_wrapper(SLOW_PATCH) + "(() => {" + SLOW_PATCH.replace("self.", "window.") + """
  const channel = new BroadcastChannel("slow");
  window.__setSlow = (pattern, ms) => {
    channel.postMessage({ pattern, ms });
    return new Promise((r) => setTimeout(r, 50));  // delivered to the worker too
  };
})();
"""


def _vertices(web) -> np.ndarray:
    return np.asarray(web.app("app.vertices()")).reshape(-1, 3)


def _luminance(colors: list[float]) -> np.ndarray:
    return np.asarray(colors).reshape(-1, 3) @ np.array([0.2126, 0.7152, 0.0722])


def _rotated_off(path, rotation: np.ndarray) -> bytes:
    """An OFF file of ``path``'s mesh with its vertices rotated."""
    lines = path.read_text().split("\n")
    n, m, _ = (int(x) for x in lines[1].split())
    vertices = np.array([[float(x) for x in line.split()] for line in lines[2:2 + n]])
    body = [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices @ rotation.T]
    return "\n".join(["OFF", lines[1], *body, *lines[2 + n:2 + n + m]]).encode() + b"\n"


# ------------------------------------------------------------------------ first view


def test_first_view_is_upright_plain_and_says_what_it_is(web):
    """Face sample: upright (its known up axis), plain colours because its forms are exact,
    a verdict in words, and a line saying what the page is for."""
    page = web.open()
    assert page.locator("#lede").is_visible()
    assert "rebuild a surface" in page.locator("#lede").inner_text()
    assert web.app("app.state.up") == "-x" and web.app("app.state.upSource") == "sample"
    up = web.app("app.screenUp()")  # the up axis points up on screen
    assert up["y"] < 0 and abs(up["x"]) < 0.2 * abs(up["y"]), up
    assert web.app("app.state.colorMode") == "plain"
    assert page.locator("#legend").is_hidden()
    verdict = page.locator("#integrability-summary").inner_text()
    report_max = web.app("app.state.integrability.max_defect")
    assert re.fullmatch(r"Forms are exact \(defect [0-9.]+e-1[0-9], round-off\)\.", verdict)
    assert report_max < 1e-12
    # Even when asked for, exact forms stay at the dark end of the ramp (round-off only).
    page.click("#show-defect")
    assert web.app("app.state.colorMode") == "defect"
    assert _luminance(web.app("app.colors()")).max() < 0.1
    assert "tolerance" in page.locator("#legend").inner_text()
    page.select_option("#color-mode", "plain")
    assert_not_blank(web.screenshot("10-first-view"), min_colored=0.0)


def test_up_axis_guessed_for_z_up_files_and_chosen_by_the_user(web, tmp_path):
    """A knight turned Z-up is shown upright (bounding-box guess); the user's choice wins."""
    page = web.open()
    turn = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # y -> z
    path = tmp_path / "knight-z-up.off"
    path.write_bytes(_rotated_off(REPO_DATA / "decimated-knight.off", turn))
    web.load_file(path)
    assert web.app("app.state.up") == "+z"
    up = web.app("app.screenUp()")
    assert up["y"] < 0 and abs(up["x"]) < 0.2 * abs(up["y"]), up
    web.screenshot("11-z-up-guessed")
    page.select_option("#up-axis", "+y")
    assert web.app("app.state.up") == "+y" and web.app("app.state.upSource") == "user"
    # Now the file's Y (the knight's front-back axis) is vertical on screen.
    y_axis = web.app("""(() => { const v = app.view, c = v.mesh.geometry.boundingSphere.center;
        const a = v.project(c.x, c.y, c.z), b = v.project(c.x, c.y + 0.1, c.z);
        return { x: b.x - a.x, y: b.y - a.y }; })()""")
    assert y_axis["y"] < 0 and abs(y_axis["x"]) < 0.2 * abs(y_axis["y"]), y_axis
    page.keyboard.press("u")  # next axis
    assert web.app("app.state.up") == "+z"


# ---------------------------------------------------------------------------- layout


def _in_view(page, selector: str, size: dict) -> bool:
    box = page.locator(selector).bounding_box()
    return (box is not None and box["y"] >= 0 and box["y"] + box["height"] <= size["height"]
            and box["x"] + box["width"] <= size["width"])


def test_main_actions_reachable_without_scrolling(web):
    """At 1400x900 and 1280x720 every tab's main actions are on screen without scrolling,
    including after a deformation (handles, histogram); each state is saved as a screenshot."""
    page = web.open()
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 640))")
    web.app("app.dragHandle(0, 0, 12)")
    wanted = {"mesh": ["#sample-select", "#mesh-file", "#integrability-summary", "#show-defect",
                       "#download-glb"],
              "deform": ["#make-handle", "#handle-list", "#undo", "#redo", "#reset-shape",
                         "#remove-handles", "#histogram", "#distortion-stats"],
              "flatten": ["#flatten"],
              "forms": ["#bend-forms", "#angle-scale"]}
    for size in (VIEWPORT, SMALL_VIEWPORT):
        page.set_viewport_size(size)
        web.frame()
        for tab, selectors in wanted.items():
            page.click(f"#tab-{tab}")
            assert page.evaluate(f"document.getElementById('panel-{tab}').scrollTop") == 0
            for selector in selectors:
                target = "label:has(#mesh-file)" if selector == "#mesh-file" else selector
                assert _in_view(page, target, size), (size, tab, selector)
            for selector in ("#view-toolbar", "#fit-view", "#up-axis", "#grid-toggle"):
                assert _in_view(page, selector, size), (size, selector)
            # the sidebar itself never scrolls (only a tab's own panel could)
            assert page.evaluate("document.querySelector('.sidebar').scrollHeight"
                                 " <= document.querySelector('.sidebar').clientHeight + 1")
    page.set_viewport_size(VIEWPORT)
    page.click("#tab-deform")
    web.screenshot("12-deform-tab")
    assert web.shown_errors() == []


def test_view_helpers_and_help_overlay(web):
    """Fit, reset view, grid and axes, wireframe and the shortcut overlay (?)."""
    page = web.open()
    start = web.app("app.view.camera.position.toArray()")
    page.mouse.move(900, 450)
    page.mouse.wheel(0, -600)  # zoom in
    web.frame()
    zoomed = web.app("app.view.camera.position.toArray()")
    assert np.linalg.norm(np.subtract(zoomed, start)) > 1
    page.keyboard.press("r")  # reset view: back to the first camera
    np.testing.assert_allclose(web.app("app.view.camera.position.toArray()"), start, rtol=1e-6)
    page.keyboard.press("g")
    assert web.app("app.view.helpers.visible") is True
    assert page.locator("#grid-toggle").is_checked()
    page.keyboard.press("m")
    assert web.app("app.view.wire.visible") is True
    web.screenshot("13-grid-wireframe")
    page.click("#wireframe")
    page.keyboard.press("?")
    help_box = page.locator("#help")
    assert help_box.is_visible()
    text = help_box.inner_text()
    for key in ("Ctrl", "H", "W", "E", "F", "R", "G", "U", "Esc", "Shift"):
        assert key in text, key
    web.screenshot("14-help")
    page.keyboard.press("Escape")
    assert help_box.is_hidden()
    page.click("#help-open")
    assert help_box.is_visible()
    page.click("#help-close")
    assert help_box.is_hidden()


# ------------------------------------------------------------------------- undo/redo


def test_undo_redo_deformation_steps(web):
    """Ctrl+Z undoes a drag (the shape before it, exactly), Ctrl+Shift+Z redoes it; undoing
    a new handle removes it, and deforming after an undo works as usual."""
    page = web.open()
    web.app("app.setRefine(false)")  # compared with linear answers (Refine is on by default)
    rest = _vertices(web)
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 620))")
    web.app("app.dragHandle(0, 0, 10)")
    first = _vertices(web)
    web.app("app.dragHandle(6, 0, 0)")
    second = _vertices(web)
    assert np.abs(second - first).max() > 1
    page.keyboard.press("Control+z")
    web.idle()
    np.testing.assert_array_equal(_vertices(web), first)
    page.click("#tab-deform")
    page.click("#undo")
    web.idle()
    np.testing.assert_allclose(_vertices(web), rest, atol=2e-4)
    page.keyboard.press("Control+Shift+z")
    web.idle()
    np.testing.assert_array_equal(_vertices(web), first)
    page.keyboard.press("Control+y")
    web.idle()
    np.testing.assert_array_equal(_vertices(web), second)
    assert page.locator("#redo").is_disabled()
    # Undo through the second handle's creation: one handle left, and a new session.
    for _ in range(3):
        page.keyboard.press("Control+z")
        web.idle()
    assert web.app("app.state.handles.length") == 1
    page.keyboard.press("Control+Shift+z")
    web.idle()
    assert web.app("app.state.handles.length") == 2
    # The session follows: a drag after undo/redo equals the API's answer for it.
    web.app("app.dragHandle(0, 4, 0)")
    body = web.app("app.deformRequest()")
    with httpx.Client(base_url=web.base, timeout=60) as http:
        session = http.post("/v1/sessions", json=body)
        assert session.status_code in (200, 201), session.text
        sid = session.json()["id"]
        try:
            solved = http.post(f"/v1/sessions/{sid}/solve", json={
                "handle_positions": [h["position"] for h in body["handles"]],
                **({"handle_rotations": [r["rotation"] for r in body["rotations"]]}
                   if body.get("rotations") else {})})
            assert solved.status_code == 200, solved.text
            want = np.asarray(solved.json()["vertices"])
        finally:
            http.delete(f"/v1/sessions/{sid}")
    np.testing.assert_allclose(_vertices(web), want, atol=2e-4)
    assert web.shown_errors() == []


# ------------------------------------------------------------------------------ bugs


def test_refused_mesh_leaves_no_stale_report(web, tmp_path):
    """A mesh /v1/mesh reads but /v1/forms refuses (coordinates of 1e100, beyond the 1e60 the
    arrays' schema admits; collinear corners and two corners at one position are accepted
    since issue 40): the panel says so instead of showing the previous mesh's report."""
    page = web.open()
    face_max = web.app("app.state.integrability.max_defect")
    page.click("#integrability-details summary")
    path = tmp_path / "degenerate.off"
    path.write_text("OFF\n4 2 0\n0 0 0\n1e100 0 0\n1e100 1e100 0\n0 1e100 0\n"
                    "3 0 1 2\n3 0 2 3\n")
    web.allow(r"status of 422")
    # Coordinates beyond float32 cannot be drawn: three.js says so when it sizes the mesh.
    web.allow(r"computeBoundingSphere\(\): Computed radius is NaN")
    page.set_input_files("#mesh-file", str(path))
    page.locator(".toast").first.wait_for()
    web.idle()
    assert web.app("app.state.name") == "degenerate.off"
    verdict = page.locator("#integrability-summary").inner_text()
    assert verdict.startswith("No report: the service refused this mesh"), verdict
    stats = page.locator("#integrability-stats").inner_text()
    assert f"{face_max:.2e}" not in stats and "Integrable" not in stats, stats
    assert web.app("app.state.integrability") is None
    assert page.locator("#bend-forms").is_disabled()
    assert web.app("app.state.colorMode") == "plain"
    assert "422" in page.locator(".toast").first.inner_text()
    web.screenshot("15-refused-mesh")


def test_no_stale_report_during_a_slow_load(web):
    """While the next mesh's report is on its way the panel says it is computing; the old
    mesh's numbers are never shown next to the new mesh."""
    web.page.add_init_script(SLOW_FETCH)
    page = web.open()
    page.click("#integrability-details summary")
    face_stats = page.locator("#integrability-stats").inner_text()
    web.evaluate("window.__setSlow('/v1/integrability', 2500)")
    page.select_option("#sample-select", "decimated-knight.off")
    web.wait_for("window.app.state.name === 'decimated-knight.off'")
    assert web.app("app.state.integrability") is None  # still on its way
    assert page.locator("#integrability-summary").inner_text().startswith("Computing")
    assert page.locator("#integrability-stats").inner_text() != face_stats
    assert "vertex defect" not in page.locator("#integrability-stats").inner_text()
    web.screenshot("16-slow-load")
    web.idle()
    assert "vertex defect" in page.locator("#integrability-stats").inner_text()
    assert page.locator("#integrability-summary").inner_text().startswith("Forms are exact")


def test_progress_bar_does_not_move_the_layout(web):
    """The progress bar floats over the view: panels, canvas and status bar keep their place."""
    web.page.add_init_script(SLOW_FETCH)
    page = web.open()
    selectors = (".sidebar", "#view-3d canvas", "#statusbar", "#tab-mesh", "#view-toolbar")

    def boxes():
        return [page.locator(s).bounding_box() for s in selectors]

    before = boxes()
    web.evaluate("window.__setSlow('/v1/forms', 2000)")
    page.select_option("#sample-select", "torus.off")
    page.locator("#progress").wait_for(state="visible")
    during = boxes()
    web.idle()
    assert page.locator("#progress").is_hidden()
    assert during == before
    assert boxes() == before


def test_distortion_legend_after_reset_shape(web):
    """After "Reset shape" the shape is back at rest: the legend shows a real range (not
    "0.00° … ≥ 0.00°") and no vertex lights up (float32 round-off stays dark)."""
    page = web.open()
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 620))")
    web.app("app.dragHandle(0, 0, 15)")
    assert _luminance(web.app("app.colors()")).max() > 0.5  # the drag lights up
    page.click("#tab-deform")
    for kind in ("Dihedral", "Edge length"):
        page.click("#reset-shape")
        web.idle()
        page.locator("#panel-deform label", has_text=kind).click()
        low = page.locator("#legend-min").inner_text()
        high = page.locator("#legend-max").inner_text()
        assert low != high and not high.startswith("≥"), (low, high)
        assert float(re.sub(r"[^0-9.]", "", high)) > 0, high
        assert _luminance(web.app("app.colors()")).max() < 0.05, kind
        assert page.locator("#legend-title").inner_text().endswith(": none")
        web.app("app.dragHandle(0, 0, 15)")
    web.screenshot("17-after-reset")


def test_toasts_close_and_do_not_repeat(web):
    """The same error twice is one toast (×2) without an echo of its detail; toasts close by
    themselves."""
    page = web.open()
    web.allow(r"status of 400")
    page.evaluate("window.app.toastMs = 1500")
    for _ in range(2):
        page.set_input_files("#mesh-file", files=[{"name": "empty.off", "mimeType": "text/plain",
                                                   "buffer": b""}])
        web.idle()
    toasts = page.locator(".toast")
    assert toasts.count() == 1
    text = toasts.first.inner_text()
    assert "\u00d72" in text and text.count("empty") == 1, text  # "the file is empty", once
    assert len(web.shown_errors()) == 2
    web.wait_for("document.querySelectorAll('.toast').length === 0", timeout=5)


def test_numbers_never_break_across_lines(web):
    """Every number in the report stays on one line (was "3.7e-↵15"), at both sizes."""
    page = web.open()
    page.click("#integrability-details summary")
    for size in (VIEWPORT, SMALL_VIEWPORT):
        page.set_viewport_size(size)
        web.frame()
        broken = page.evaluate("""() => {
            const out = [];
            for (const id of ['integrability-stats', 'mesh-stats']) {
              const walker = document.createTreeWalker(document.getElementById(id),
                                                       NodeFilter.SHOW_TEXT);
              for (let node = walker.nextNode(); node; node = walker.nextNode()) {
                for (const m of node.textContent.matchAll(/[-+]?[0-9][0-9.,]*(?:e[-+]?[0-9]+)?/g)) {
                  const range = document.createRange();
                  range.setStart(node, m.index);
                  range.setEnd(node, m.index + m[0].length);
                  const tops = new Set([...range.getClientRects()].map((r) => Math.round(r.top)));
                  if (tops.size > 1) out.push(m[0]);
                }
              }
            }
            return out; }""")
        assert broken == [], (size, broken)
    text = page.locator("#integrability-stats").inner_text()
    assert re.search(r"Worst\s+v\d+: [0-9.]+e-\d+", text), text


def test_flatten_offered_on_closed_meshes(web):
    page = web.open()
    page.click("#tab-flatten")
    assert page.locator("#flatten").is_enabled()  # the face is a disk
    page.click("#tab-mesh")
    page.select_option("#sample-select", "decimated-knight.off")
    web.wait_for("window.app.state.name === 'decimated-knight.off'")
    web.idle()
    page.click("#tab-flatten")
    assert page.locator("#flatten").is_enabled()  # cut into charts (issue 41)
    assert "seams" in page.locator("#flatten-note").inner_text()
    web.screenshot("18-flatten-closed")


JARGON = re.compile(r"/v1/|WebSocket|Backend|\bPOST\b|\bHTTP\b|\bnone\b|session", re.I)


def test_no_jargon_shown(web):
    """What a user reads while deforming and rebuilding: no endpoint paths, transport
    names or backend identifiers."""
    page = web.open()
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 620))")
    web.app("app.dragHandle(0, 0, 8)")
    assert "WebSocket" in web.app("app.state.transport.label")  # it is there, just not shown
    page.click("#tab-deform")
    shown = page.evaluate("document.body.innerText")
    assert not JARGON.search(shown), JARGON.search(shown)
    assert "Live:" in page.locator("#transport").inner_text()
    page.click("#tab-forms")
    page.click("#bend-forms")
    web.wait_for("window.app.state.source === 'reconstruction'")
    web.idle()
    shown = page.evaluate("document.body.innerText")
    assert not JARGON.search(shown), JARGON.search(shown)
    assert "Method" in page.locator("#forms-stats").inner_text()
    web.screenshot("19-rebuilt")


# --------------------------------------------------------------------- rebuild, refined


def test_rebuild_shows_refined_answer_and_compares_linear(web):
    """Knight, angles x 0.8: the page shows the refined answer (the service's default), lists
    both residuals, and its Linear switch shows the linear answer (refine: false), which
    shrinks the knight."""
    page = web.open("?sample=decimated-knight.off")
    if not web.app("app.capabilities.refine"):
        pytest.skip("this server's reconstruct has no options.refine")
    source = _vertices(web)
    page.click("#tab-forms")
    page.fill("#angle-scale", "0.8")
    page.click("#bend-forms")
    web.wait_for("window.app.state.source === 'reconstruction'")
    web.idle()
    forms = web.app("app.state.reconstruction.input")
    with httpx.Client(base_url=web.base, timeout=120) as http:
        refined = http.post("/v1/reconstruct", json=forms).json()
        linear = http.post("/v1/reconstruct", json={**forms, "options": {"refine": False}}).json()
    assert refined["report"]["refinement"]["refined"] is True
    # Both answers are shown placed on the knight they were rebuilt from.
    np.testing.assert_allclose(_vertices(web), rigid_align(refined["vertices"], source),
                               atol=1e-6)
    table = page.locator("#residuals").inner_text()
    before = refined["report"]["refinement"]["before"]
    after = refined["report"]["refinement"]["after"]
    for summary in (before, after):  # both answers' max length error, as the page formats it
        assert f"{100 * summary['length_error']['max']:.2f} %" in table, table
    assert after["length_error"]["max"] < before["length_error"]["max"]
    assert page.locator("#forms-note").inner_text().find("Switch to Linear") >= 0
    web.screenshot("20-rebuild-refined")

    page.locator("#compare-row label", has_text="Linear").click()
    web.idle()
    np.testing.assert_allclose(_vertices(web), rigid_align(linear["vertices"], source),
                               atol=1e-6)
    assert "linear answer" in page.locator("#forms-stats").inner_text()
    size = lambda v: np.ptp(np.asarray(v), axis=0).max()  # noqa: E731
    assert size(linear["vertices"]) < 0.5 * size(refined["vertices"])  # the collapse
    web.screenshot("21-rebuild-linear")
    page.locator("#compare-row label", has_text="Refined").click()
    web.idle()
    np.testing.assert_allclose(_vertices(web), rigid_align(refined["vertices"], source),
                               atol=1e-6)
    assert web.shown_errors() == []


def test_refined_drags(web):
    """With Refine on, the session is opened with options.refine and drags still land on
    their handle targets."""
    page = web.open()
    if not web.app("app.capabilities.deformRefine"):
        pytest.skip("this server's deform has no options.refine")
    page.click("#tab-deform")
    assert page.locator("#deform-refine").is_visible()
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 620))")
    web.app("app.setRefine(true)")
    web.app("app.dragHandle(0, 0, 12)")
    body = web.app("app.deformRequest()")
    assert body["options"]["refine"] is True
    got = _vertices(web)
    handles = [h["vertex"] for h in body["handles"]]
    targets = np.asarray([h["position"] for h in body["handles"]])
    np.testing.assert_allclose(got[handles], targets, atol=2e-4)
    assert web.shown_errors() == []
