"""What a newcomer hits (issue 43), in a real browser against a real uvicorn: the page
survives reloads that revalidate its cached scripts (the 304 answers carry the same security
headers as the 200s), every HTML page's Content-Security-Policy names no external source."""

from __future__ import annotations

import os
import re
import subprocess
import sys

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
    # The worker (js/worker.js, revalidated) read the mesh and computed its report.
    assert web.page.evaluate("window.app.state.integrability !== null")
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
    # A scheme source (ws:, https:) names every host of that scheme; data: and blob: are
    # this document's own.
    schemes = {t for t in policy.replace(";", " ").split() if t.endswith(":")}
    assert schemes <= {"data:", "blob:"}, policy


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


# ------------------------------------------------------------------ warnings on the page


def _bend_forms(web, page, scale: str = "0.8") -> None:
    """Rebuild the shown mesh from its forms with the dihedral angles scaled by ``scale``
    (the Forms tab), and wait for the reconstruction."""
    page.click("#tab-forms")
    page.fill("#angle-scale", scale)
    page.click("#bend-forms")
    web.wait_for("window.app.state.source === 'reconstruction'", timeout=180)
    web.idle()


def test_rebuild_panel_shows_the_answers_warnings(web) -> None:
    """Face, angles x 0.8: the refined answer is 0.14 rad from the bent forms at worst,
    past the 0.1 rad limit; the panel lists the warning, whose value is the largest
    dihedral-angle error of the shown surface against the forms (measured here); angles x 1
    rebuilds the face exactly and the list is hidden."""
    import numpy as np

    import solver
    from solver.mesh.metrics import wrap_angle
    from solver.mesh.topology import build_topology

    page = web.open()
    _bend_forms(web, page)
    box = page.locator("#forms-warnings")
    assert box.is_visible()
    warnings = web.app("app.state.reconstruction.report.warnings")
    angle = next(w for w in warnings if w["code"] == "angle-error")
    assert angle["message"] in box.inner_text()
    assert "rad (" in angle["message"] and "°" in angle["message"]
    forms = web.app("app.state.reconstruction.input")
    shown = np.asarray(web.app("app.vertices()")).reshape(-1, 3)
    faces = np.asarray(forms["faces"])
    got = solver.fundamental_forms(shown, faces)
    np.testing.assert_array_equal(got.edges, np.asarray(forms["edges"]))
    interior = build_topology(faces, len(shown)).interior_edges
    measured = np.abs(wrap_angle(got.angles - np.asarray(forms["angles"]))[interior]).max()
    assert abs(angle["value"] - measured) < 1e-6
    assert "Outcome" in page.locator("#forms-stats").inner_text()
    assert "converged after" in page.locator("#forms-stats").inner_text()
    page.fill("#angle-scale", "1")
    page.click("#bend-forms")
    web.wait_for("window.app.state.reconstruction.report.warnings.length === 0", timeout=180)
    web.idle()
    assert box.is_hidden()


# ------------------------------------------------------------------- handle sets as files


def _ffs(*args: str, cwd) -> subprocess.CompletedProcess[str]:
    from tests.helpers import REPO

    env = {k: v for k, v in os.environ.items() if k != "FFS_SERVER"}
    env["PYTHONPATH"] = str(REPO)
    return subprocess.run([sys.executable, "-m", "ffs", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300, env=env)


def test_handles_export_to_ffs_and_import_back(web, tmp_path) -> None:
    """Two handles on the face (one pinned, one moved and turned): Export handles writes the
    targets the page solves for, ffs deform reads the file and puts those vertices there,
    and Import handles on a fresh page rebuilds the same handles at the same targets."""
    import json

    import numpy as np
    import trimesh

    from tests.helpers import REPO

    page = web.open()
    rest = np.asarray(web.app("app.vertices()")).reshape(-1, 3)
    sample = REPO / "service" / "static" / "samples" / "face.off"
    np.testing.assert_array_equal(
        rest, np.asarray(trimesh.load(sample, process=False).vertices))
    page.click("#tab-deform")
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 606))")
    web.app("app.dragHandle(5, -4, 12, {axis: [1, 0, 0], angle: 0.2})")
    targets = np.asarray(web.app("app.handleTargets().positions")).reshape(-1, 3)
    groups = web.app("app.state.handles.map((h) => h.vertices)")
    with page.expect_download() as info:
        page.click("#export-handles")
    saved = tmp_path / "face-handles.json"
    info.value.save_as(saved)
    doc = json.loads(saved.read_text())
    assert [h["vertex"] for h in doc["handles"]] == [v for g in groups for v in g]
    np.testing.assert_allclose([h["position"] for h in doc["handles"]], targets, atol=1e-12)
    assert [g["vertices"] for g in doc["groups"]] == groups and doc["rotations"]

    run = _ffs("deform", str(sample), "--handles", str(saved), "-o", "out.ply", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    out = np.asarray(trimesh.load(tmp_path / "out.ply", process=False).vertices)
    handle_vertices = [h["vertex"] for h in doc["handles"]]
    np.testing.assert_allclose(out[handle_vertices], targets, atol=1e-6 * np.ptp(rest))

    page.goto("about:blank")
    web.open()
    page.click("#tab-deform")
    page.set_input_files("#handles-file", str(saved))
    web.wait_for("window.app.state.handles.length === 2", timeout=60)
    web.idle()
    assert web.app("app.state.handles.map((h) => h.vertices)") == groups
    assert web.app("app.state.handles.map((h) => h.id)") == [1, 2]
    again = np.asarray(web.app("app.handleTargets().positions")).reshape(-1, 3)
    np.testing.assert_allclose(again, targets, atol=1e-9 * np.ptp(rest))
    shown = np.asarray(web.app("app.vertices()")).reshape(-1, 3)
    np.testing.assert_allclose(shown[handle_vertices], targets, atol=1e-4 * np.ptp(rest))
    assert web.shown_errors() == []


def test_import_of_a_bad_handle_file_says_why(web, tmp_path) -> None:
    page = web.open()
    page.click("#tab-deform")
    bad = tmp_path / "bad.json"
    bad.write_text('[{"vertex": 99999, "position": [0, 0, 0]}]')
    web.allow(r"Not a handle set")
    page.set_input_files("#handles-file", str(bad))
    web.wait_for("window.app.state.errors.length > 0", timeout=30)
    error = web.shown_errors()[-1]
    assert error["title"] == "Not a handle set"
    assert "vertex 99999 is not a vertex of this mesh (0 to 1179)" in error["detail"]
    assert web.app("app.state.handles.length") == 0


# -------------------------------------------------------- the colour map of a rebuilt surface


def test_rebuilt_surface_is_coloured_by_the_forms_being_rebuilt(web) -> None:
    """Face, angles x 0.8: the rebuilt surface's own forms are exact, so its defect map was
    empty; the map now shows the bent forms' per-vertex defect (measured here with the
    library), the legend says so and its title fits in its box."""
    import numpy as np

    import solver

    page = web.open()
    _bend_forms(web, page)
    assert web.app("app.state.colorMode") == "defect"
    forms = web.app("app.state.reconstruction.input")
    truth = solver.check_integrability(np.asarray(forms["faces"]), np.asarray(forms["edges"]),
                                       np.asarray(forms["lengths"]),
                                       np.asarray(forms["angles"]))
    assert not truth.integrable and truth.max_defect > 0.1
    rgb = np.asarray(web.app("app.colors()")).reshape(-1, 3)
    luminance = rgb @ np.array([0.2126, 0.7152, 0.0722])
    values = np.asarray(truth.vertex_defect)
    above = values > truth.tolerance  # below the tolerance the ramp is flat (dark)
    ranks = [np.argsort(np.argsort(x)) for x in (np.log10(values[above]), luminance[above])]
    assert np.corrcoef(*ranks)[0, 1] > 0.99
    assert np.ptp(luminance) > 0.3  # not one colour: the map is not empty
    title = page.locator("#legend-title")
    assert "of the forms being rebuilt" in title.inner_text()
    fits = page.evaluate("""() => { const t = document.getElementById('legend-title');
        const box = document.getElementById('legend').getBoundingClientRect();
        const r = t.getBoundingClientRect();
        return t.scrollWidth <= t.clientWidth && r.left >= box.left && r.right <= box.right; }""")
    assert fits
    page.click("#tab-mesh")
    assert "defects of the forms it was rebuilt from" in page.locator(
        "#integrability-note").inner_text()


# ----------------------------------------------------------------------- page details (8)

RECORD_TRANSPORT = """() => { window.__seen = [];
  const note = () => window.__seen.push({
    text: document.getElementById('transport').textContent,
    preparing: !document.getElementById('progress').hidden
      && document.getElementById('progress-label').textContent.includes('Preparing') });
  new MutationObserver(note).observe(document.body,
    { subtree: true, childList: true, characterData: true, attributes: true });
  return true; }"""


def test_no_old_timing_beside_the_preparation(web) -> None:
    """Adding a handle prepares a new deformation: the panel says so, never the previous
    deformation's "ms per update" while "Preparing the deformation" is shown."""
    page = web.open()
    page.click("#tab-deform")
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 606))")
    web.app("app.dragHandle(0, 0, 5)")
    assert "ms per update" in page.locator("#transport").inner_text()
    page.evaluate(RECORD_TRANSPORT)
    web.app("app.makeHandle(app.visibleVertices().slice(300, 304))")
    seen = page.evaluate("window.__seen")
    preparing = [s["text"] for s in seen if s["preparing"]]
    assert preparing, seen  # the preparation was seen
    assert not any("ms per update" in text for text in preparing), preparing
    assert any("Setting up the live deformation" in text for text in preparing), preparing
    web.app("app.dragHandle(0, 0, 2)")
    assert "ms per update" in page.locator("#transport").inner_text()


def test_handles_are_numbered_per_mesh(web) -> None:
    page = web.open()
    page.click("#tab-deform")
    for ids in ([0, 1], [600, 601], [300, 301]):
        web.app("app.makeHandle(arg)", ids)
    assert "Handle 3" in page.locator("#handle-list").inner_text()
    web.app("app.loadSample('decimated-knight.off')")
    web.idle()
    page.click("#tab-deform")
    web.app("app.makeHandle([0, 1])")
    names = page.locator("#handle-list").inner_text()
    assert "Handle 1" in names and "Handle 4" not in names, names


GIZMO_TOP = """() => { const view = app.view; const root = view.gizmo.getHelper();
  root.updateMatrixWorld(true);
  const gizmo = root.children.find((c) => c.gizmo);
  const shown = (o) => { for (let x = o; x; x = x.parent) if (!x.visible) return false;
                         return true; };
  let top = Infinity;
  gizmo.gizmo[view.gizmo.mode].traverse((o) => {
    if (!o.geometry || !shown(o)) return;
    const p = o.geometry.getAttribute('position');
    for (let i = 0; i < p.count; i++) {
      const v = new view.camera.position.constructor(p.getX(i), p.getY(i), p.getZ(i))
        .applyMatrix4(o.matrixWorld);
      top = Math.min(top, view.project(v.x, v.y, v.z).y);
    }
  });
  return top; }"""
MESH_TOP = """() => { const v = app.state.vertices; let top = Infinity;
  for (let i = 0; i < v.length; i += 3) top = Math.min(top, app.view.project(v[i], v[i + 1],
    v[i + 2]).y);
  return top; }"""


def test_fit_keeps_the_mesh_and_the_gizmo_below_the_toolbar(web) -> None:
    """At 1280 x 720 the face's and the knight's tops were under the floating toolbar after
    Fit (F); with a handle at the top of the shape, so was its gizmo."""
    from tests.helpers.web import SMALL_VIEWPORT

    page = web.open()
    page.set_viewport_size(SMALL_VIEWPORT)
    bar = "document.getElementById('view-toolbar').getBoundingClientRect().bottom"
    for sample in ("face.off", "decimated-knight.off"):
        web.app("app.loadSample(arg)", sample)
        web.idle()
        page.click("#tab-mesh")
        page.keyboard.press("f")
        web.frame()
        assert web.app(f"({MESH_TOP})()") > page.evaluate(bar), sample
    page.click("#tab-deform")
    topmost = web.app("""(() => { const v = app.state.vertices; let best = 0, y = Infinity;
        for (let i = 0; i < v.length / 3; i++) { const p = app.view.project(v[3 * i],
          v[3 * i + 1], v[3 * i + 2]); if (p.y < y) { y = p.y; best = i; } }
        return best; })()""")
    web.app("app.makeHandle(arg)", [topmost])
    page.keyboard.press("f")
    web.frame()
    assert web.app(f"({MESH_TOP})()") > page.evaluate(bar)
    assert web.app(f"({GIZMO_TOP})()") > page.evaluate(bar)


def test_linear_answer_note_and_empty_angle_scale(web) -> None:
    page = web.open("?sample=decimated-knight.off")
    _bend_forms(web, page)
    assert "the refined one shown here" in page.locator("#forms-note").inner_text()
    page.locator("#compare-row label", has_text="Linear").click()
    web.wait_for("window.app.state.reconstruction.showing === 'linear'", timeout=120)
    web.idle()
    note = page.locator("#forms-note").inner_text()
    assert "The linear answer shown here" in note and "refined one shown here" not in note
    before = web.app("app.state.name")
    page.fill("#angle-scale", "")
    page.click("#bend-forms")
    web.wait_for("window.app.state.errors.length > 0", timeout=30)
    error = web.shown_errors()[-1]
    assert error["title"] == "Invalid angle scale" and "empty" in error["detail"]
    assert web.app("app.state.name") == before  # nothing was rebuilt


# ------------------------------------------------------------- warnings on the Flatten tab


def _strips_obj(path) -> None:
    """Two flat strips 40 x 1 side by side (two parts): each flattens exactly, but two long
    charts leave most of the unit square empty."""
    import numpy as np
    import trimesh

    x = np.linspace(0.0, 40.0, 41)
    i = np.arange(40)
    strip = np.concatenate([np.stack([i, i + 1, i + 41], 1), np.stack([i + 1, i + 42, i + 41], 1)])
    parts = [np.concatenate([np.stack([x, x * 0 + y, x * 0], 1),
                             np.stack([x, x * 0 + y + 1, x * 0], 1)]) for y in (0.0, 3.0)]
    trimesh.Trimesh(np.concatenate(parts), np.concatenate([strip, strip + 82]),
                    process=False).export(path)


def test_flatten_panel_lists_the_answers_warnings(web, tmp_path) -> None:
    """The Flatten tab's answer past a documented threshold (packing efficiency under 40%)
    lists the warning under its figures, with the value the page's own texcoords give."""
    import numpy as np

    path = tmp_path / "strips.obj"
    _strips_obj(path)
    page = web.open()
    web.load_file(path)
    page.click("#tab-flatten")
    page.click("#flatten")
    web.wait_for("window.app.state.flat !== null", timeout=120)
    web.idle()
    box = page.locator("#flatten-warnings")
    assert box.is_visible()
    warnings = web.app("app.state.flat.report.warnings")
    assert [w["code"] for w in warnings] == ["packing-efficiency"]
    assert warnings[0]["message"] in box.inner_text()
    texcoords = np.asarray(web.app("Array.from(app.state.flat.atlas.texcoords)")).reshape(-1, 2)
    faces = np.asarray(web.app("Array.from(app.state.flat.atlas.uvFaces)")).reshape(-1, 3)
    a, b, c = (texcoords[faces[:, k]] for k in range(3))
    covered = 0.5 * np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]).sum()
    assert covered < 0.4 and abs(warnings[0]["value"] - (1 - covered)) < 1e-5
    assert web.shown_errors() == []
