"""The web page at / in a real browser (headless Debian Chromium via Playwright) against a
real uvicorn: open meshes, the defect map, live deformation through the session WebSocket
(and its HTTP fallbacks), flattening, reconstruction from forms, the GLB download and the
error messages. Results the page shows are checked against direct API calls; screenshots are
saved to tests/artifacts/web/ and must not be blank.
"""

from __future__ import annotations

import io
import json
import re

import httpx
import numpy as np
import pytest

from tests.helpers.web import ARTIFACTS, assert_not_blank

REPO_DATA = ARTIFACTS.parents[1] / "data"


def _api(web) -> httpx.Client:
    return httpx.Client(base_url=web.base, timeout=60)


def _canvas_png(web, selector: str = "#view-3d canvas") -> bytes:
    return web.page.locator(selector).screenshot()


def _vertices(web) -> np.ndarray:
    return np.asarray(web.app("app.vertices()")).reshape(-1, 3)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def _luminance(colors: list[float]) -> np.ndarray:
    rgb = np.asarray(colors).reshape(-1, 3)
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


# ------------------------------------------------------------------------------ opening


def test_page_served_and_assets_offline(web_server):
    with httpx.Client(base_url=web_server, timeout=10) as http:
        page = http.get("/")
        assert page.status_code == 200 and "text/html" in page.headers["content-type"]
        assert 'type="importmap"' in page.text and "/static/vendor/three/" in page.text
        assert "//cdn" not in page.text and "https://" not in page.text  # nothing external
        for path in ("/static/js/main.js", "/static/vendor/three/three.module.js",
                     "/static/vendor/three/three.core.js",
                     "/static/vendor/three/addons/controls/TransformControls.js",
                     "/static/samples/index.json", "/favicon.ico"):
            assert http.get(path).status_code == 200, path
        assert http.get("/docs").status_code == 200  # the API docs stay where they were
        assert "/" not in http.get("/openapi.json").json()["paths"]


def test_upload_mesh_and_defect_map(web):
    """Upload a mesh file, see the integrability defect as a colour map with the numbers of
    the API's report; the Gauss and Codazzi parts are selectable."""
    page = web.open()
    assert web.app("app.state.name") == "face.off"  # the default sample
    web.load_file(REPO_DATA / "decimated-knight.off")
    assert web.app("app.state.colorMode") == "plain"  # exact forms: nothing to colour
    assert page.locator("#integrability-summary").inner_text().startswith("Forms are exact")
    page.click("#show-defect")
    assert web.app("app.state.colorMode") == "defect"

    data = (REPO_DATA / "decimated-knight.off").read_bytes()
    with _api(web) as api:
        mesh = api.post("/v1/mesh", files={"file": ("knight.off", data)}).json()
        forms = api.post("/v1/forms", json={"vertices": mesh["vertices"],
                                            "faces": mesh["faces"]}).json()
        report = api.post("/v1/integrability", json=forms).json()
    np.testing.assert_array_equal(_vertices(web), np.asarray(mesh["vertices"]))
    page.click("#integrability-details summary")
    stats = page.locator("#integrability-stats").inner_text()
    vertex_max = np.abs(report["vertex_defect"]).max()
    assert f"Total vertex defect (max)\n{vertex_max:.2e} rad" in stats, stats
    assert "Integrable" in stats and "yes" in stats
    assert page.locator("#legend-title").inner_text().startswith("Total defect")

    # The colours follow the per-vertex defect (viridis: brighter = larger).
    for part, label in (("vertex_defect", "Total"), ("gauss_defect", "Gauss"),
                        ("codazzi_defect", "Codazzi")):
        page.locator("#panel-mesh .segmented label", has_text=label).click()
        assert page.locator("#legend-title").inner_text().startswith(f"{label} defect")
        values = np.asarray(report[part])
        lum = _luminance(web.app("app.colors()"))
        positive = values > 0
        assert _spearman(np.log10(values[positive]), lum[positive]) > 0.99, part
    page.locator("#panel-mesh .segmented label", has_text="Total").click()
    png = web.screenshot("01-defect-map")
    assert_not_blank(png)
    assert_not_blank(_canvas_png(web))
    assert web.shown_errors() == []


# ---------------------------------------------------------------------------- deforming


def _check_against_deform(web, orthonormalize: bool) -> np.ndarray:
    """The page's vertices equal POST /v1/deform for the page's current handles."""
    body = web.app("app.deformRequest()")
    assert body["options"]["orthonormalize"] is orthonormalize
    with _api(web) as api:
        response = api.post("/v1/deform", json=body)
    assert response.status_code == 200, response.text
    want = np.asarray(response.json()["vertices"])
    got = _vertices(web)
    np.testing.assert_allclose(got, want, atol=2e-4)  # float32 vertices over the socket
    handles = [h["vertex"] for h in body["handles"]]
    targets = np.asarray([h["position"] for h in body["handles"]])
    np.testing.assert_allclose(got[handles], targets, atol=2e-4)  # hard constraints
    return got


def test_deform_with_mouse_and_gizmo(web):
    """Click a vertex, box-select a region, make two handles, drag the gizmo with the mouse:
    the mesh follows live through the session WebSocket exactly as POST /v1/deform says;
    rotation and orthonormalization too; distortion map and histogram are drawn."""
    page = web.open()
    web.app("app.setRefine(false)")  # compared with linear answers (Refine is on by default)
    rest = _vertices(web)
    assert web.app("app.capabilities.sessions") is True

    # A real click on a vertex near the middle of the view.
    canvas = page.locator("#view-3d canvas").bounding_box()
    cx, cy = canvas["x"] + canvas["width"] / 2, canvas["y"] + canvas["height"] / 2
    visible = web.app("app.visibleVertices()")
    screen = {v: web.app("app.screenOf(arg)", v) for v in visible[::7]}
    target = min(screen, key=lambda v: (screen[v]["x"] - cx + 150) ** 2
                 + (screen[v]["y"] - cy) ** 2)
    page.mouse.click(screen[target]["x"], screen[target]["y"])
    selection = web.app("app.state.selection")
    assert len(selection) == 1
    picked = web.app("app.screenOf(arg)", selection[0])
    assert abs(picked["x"] - screen[target]["x"]) + abs(picked["y"] - screen[target]["y"]) < 8
    page.click("#make-handle")
    web.idle()
    assert web.app("app.state.handles.length") == 1

    # A real Shift + drag box selection on the other side, then the second handle.
    x0, y0 = cx + 90, cy - 40
    page.keyboard.down("Shift")
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move(x0 + 70, y0 + 70, steps=4)
    page.mouse.up()
    page.keyboard.up("Shift")
    boxed = web.app("app.state.selection")
    assert len(boxed) >= 3
    for v in boxed:
        p = web.app("app.screenOf(arg)", v)
        assert x0 - 1 <= p["x"] <= x0 + 71 and y0 - 1 <= p["y"] <= y0 + 71
    assert page.locator("#selection-count").inner_text() == f"{len(boxed)} selected"
    page.click("#make-handle")
    web.idle()
    assert web.app("app.state.handles.length") == 2
    assert "WebSocket" in web.app("app.state.transport.label")
    assert page.locator("#transport").inner_text().startswith("Live:")

    # A real drag of the active handle's gizmo (its centre moves in the view plane).
    pivot = web.app("app.pivotScreen()")
    page.mouse.move(pivot["x"], pivot["y"])
    page.mouse.down()
    page.mouse.move(pivot["x"] + 40, pivot["y"] - 60, steps=6)
    page.mouse.up()
    web.idle()
    moved = _check_against_deform(web, orthonormalize=False)
    second = web.app("app.state.handles[1].vertices")
    shift = np.linalg.norm(moved[second] - rest[second], axis=1)
    assert shift.min() > 1.0, shift  # the handle region followed the mouse
    assert np.abs(moved - rest).max() > 1.0
    assert web.app("app.state.solves") >= 2

    # Programmatic drag with a rotation: the gizmo's rotate mode does the same.
    page.locator("#panel-deform label", has_text="Rotate").click()
    web.app("app.dragHandle(0, 8, -6, {axis: [0, 1, 0], angle: 0.35})")
    _check_against_deform(web, orthonormalize=False)

    # Distortion: colour map, numbers equal to the library's metrics, histogram drawn.
    assert web.app("app.state.colorMode") == "distortion"
    import solver.mesh.metrics

    want = solver.mesh.metrics.distortion(rest, _vertices(web), np.asarray(
        web.app("Array.from(app.state.faces)")).reshape(-1, 3))
    summary = web.app("app.state.distortion.lengthSummary")
    for key in ("mean", "rms", "max", "p95"):
        assert summary[key] == pytest.approx(want["length_summary"][key], rel=1e-3, abs=1e-6)
    summary = web.app("app.state.distortion.angleSummary")
    for key in ("mean", "max"):
        assert summary[key] == pytest.approx(want["angle_summary"][key], rel=1e-3, abs=1e-6)
    drawn = page.evaluate("""() => { const c = document.getElementById('histogram');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }""")
    assert drawn > 2000
    assert "Max" in page.locator("#distortion-stats").inner_text()
    page.locator("#panel-deform label", has_text="Dihedral").click()
    assert page.locator("#legend-title").inner_text().startswith("Dihedral")

    # Orthonormalization: a new session with the option, same answer as the API.
    page.locator("label.check", has_text="Orthonormalize").first.click()
    web.idle()
    assert web.app("app.state.orthonormalize") is True
    _check_against_deform(web, orthonormalize=True)

    png = web.screenshot("02-deform")
    assert_not_blank(png)
    assert web.shown_errors() == []

    # Reset: back to the rest shape (the handles stay).
    page.click("#reset-shape")
    web.idle()
    np.testing.assert_allclose(_vertices(web), rest, atol=2e-4)


@pytest.mark.parametrize("transport", ["http", "deform"])
def test_deform_fallbacks(web, transport):
    """Without the WebSocket (POST /v1/sessions/{id}/solve) and without sessions (POST
    /v1/deform per update) the page deforms the same way."""
    page = web.open(f"?transport={transport}")
    web.app("app.setRefine(false)")  # compared with linear answers (Refine is on by default)
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 606))")
    web.app("app.dragHandle(5, -4, 12, {axis: [1, 0, 0], angle: 0.2})")
    label = web.app("app.state.transport.label")
    assert ("/solve" in label) if transport == "http" else ("/v1/deform" in label), label
    _check_against_deform(web, orthonormalize=False)
    assert page.locator("#distortion-stats").inner_text()
    assert web.shown_errors() == []


def test_session_gone_is_replaced(web):
    """A session that expired (or whose worker died) is replaced on the next drag: the page
    opens a new one for the same handles and the drag lands, with no error to show."""
    web.open()
    web.app("app.setRefine(false)")  # compared with linear answers (Refine is on by default)
    web.app("app.makeHandle([0, 1])")
    web.app("app.makeHandle([600])")
    first = web.app("app.state.transport.id")
    with _api(web) as api:
        assert api.delete(f"/v1/sessions/{first}").status_code == 204  # as if it expired
    web.app("app.dragHandle(0, 0, 6)")
    assert web.app("app.state.transport.id") not in (None, first)
    assert "WebSocket" in web.app("app.state.transport.label")
    _check_against_deform(web, orthonormalize=False)
    assert web.shown_errors() == []


# ---------------------------------------------------------------------------- flattening


def test_flatten_with_progress_and_download_glb(web, tmp_path):
    """Flatten runs as a job with a progress bar; the layout (checkerboard, flips) equals the
    API's; the current mesh downloads as a valid GLB."""
    from tests.helpers.gltf_validator import validate_gltf

    page = web.open()
    page.keyboard.press("3")  # the Flatten tab
    page.evaluate("""() => { window.__progress = [];
        new MutationObserver(() => window.__progress.push(
            document.getElementById('progress-label').textContent))
          .observe(document.getElementById('progress-label'), {childList: true}); }""")
    page.click("#flatten")
    web.wait_for("window.app.state.flat !== null")
    web.idle()
    labels = page.evaluate("window.__progress")
    assert any(label.startswith("Flatten:") and "%" in label for label in labels), labels
    assert page.locator("#progress").is_hidden()
    assert page.locator("#view-flat").is_visible()

    body = {"vertices": _vertices(web).tolist(),
            "faces": np.asarray(web.app("Array.from(app.state.faces)")).reshape(-1, 3).tolist(),
            "options": {"orthonormalize": True}}
    with _api(web) as api:
        want = api.post("/v1/parameterize", json=body).json()
    uv = np.asarray(web.app("Array.from(app.state.flat.uv)")).reshape(-1, 2)
    np.testing.assert_allclose(uv, np.asarray(want["uv"]), atol=1e-6 * np.ptp(uv))
    assert web.app("app.state.flat.flipped") == want["flipped_faces"]
    note = page.locator("#flip-note").inner_text()
    flips = len(want["flipped_faces"])
    assert note == (f"{flips} flipped face(s) in red" if flips else "no flipped faces")
    assert web.app("app.state.colorMode") == "checker"
    png = web.screenshot("03-flatten")
    assert_not_blank(png)
    assert_not_blank(_canvas_png(web, "#view-flat canvas"), min_colored=0.05)

    # Download the current mesh as GLB and validate it.
    web.app("app.makeHandle([0])")
    web.app("app.makeHandle([600])")
    web.app("app.dragHandle(0, 0, 10)")
    page.click("#tab-mesh")
    with page.expect_download() as info:
        page.click("#download-glb")
    download = info.value
    assert download.suggested_filename == "face.glb"
    path = tmp_path / "face.glb"
    download.save_as(path)
    glb = path.read_bytes()
    (ARTIFACTS / "download.glb").write_bytes(glb)
    report = validate_gltf(glb, "glb")
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    import trimesh

    scene = trimesh.load(io.BytesIO(glb), file_type="glb", process=False)
    mesh = next(iter(scene.geometry.values()))
    np.testing.assert_allclose(mesh.vertices, _vertices(web), atol=1e-4)
    np.testing.assert_array_equal(
        mesh.faces, np.asarray(web.app("Array.from(app.state.faces)")).reshape(-1, 3))
    assert web.shown_errors() == []


# ----------------------------------------------------------------------- forms -> mesh


def test_reconstruct_from_forms_file(web, tmp_path):
    """Upload a forms JSON (the /v1/forms output, here with bent angles): the page shows the
    API's reconstruction and the (failed) integrability report."""
    data = (REPO_DATA / "torus.off").read_bytes()
    with _api(web) as api:
        forms = api.post("/v1/forms", files={"file": ("torus.off", data)}).json()
        forms["angles"] = [0.9 * a for a in forms["angles"]]
        want = api.post("/v1/reconstruct", json=forms).json()
        report = api.post("/v1/integrability", json=forms).json()
    path = tmp_path / "torus-bent-forms.json"
    path.write_text(json.dumps(forms))
    page = web.open()
    page.set_input_files("#forms-file", str(path))
    web.wait_for("window.app.state.source === 'reconstruction'")
    web.idle()
    assert web.app("app.state.name") == "torus-bent-forms.json (reconstructed)"
    np.testing.assert_allclose(_vertices(web), np.asarray(want["vertices"]), atol=1e-6)
    assert report["integrable"] is False
    # The Rebuild panel reports the forms (they do not fit), the Mesh panel the shown mesh.
    stats = page.locator("#forms-stats").inner_text()
    assert re.search(r"Forms integrable\s+no", stats), stats
    vertex_max = np.abs(report["vertex_defect"]).max()
    assert f"{float(f'{vertex_max:.3g}'):g} rad" in stats, stats
    loops = report["global_holonomy"]["rotation"] + report["global_holonomy"]["translation"]
    assert f"{sum(g['passes'] for g in loops)} / {len(loops)} pass" in stats  # genus 1
    assert "Rebuilt" in stats
    assert web.app("app.state.integrability.integrable") is True
    assert page.locator("#integrability-summary").inner_text().startswith("Forms are exact")
    assert web.app("app.state.tab") == "forms"
    # Coloured by the forms being rebuilt (not integrable), not by the shown mesh's own
    # exact forms (issue 43: the map was empty after a rebuild).
    assert web.app("app.state.colorMode") == "defect"
    png = web.screenshot("04-forms")
    assert_not_blank(png)
    assert web.shown_errors() == []


# ------------------------------------------------------------------------------- errors


def test_api_errors_are_shown(web, tmp_path):
    """Problem documents become readable messages; nothing is swallowed."""
    page = web.open()
    web.allow(r"Failed to load resource: the server responded with a status of 415")
    web.allow(r"Failed to load resource: the server responded with a status of 422")

    page.set_input_files("#mesh-file", files=[{"name": "notes.txt", "mimeType": "text/plain",
                                               "buffer": b"not a mesh"}])
    toast = page.locator(".toast").first
    toast.wait_for()
    assert "415" in toast.inner_text() and "not a supported mesh file" in toast.inner_text()
    assert web.app("app.state.name") == "face.off"  # the open mesh is kept

    # A closed mesh is flattened into an atlas (tests/web/test_flatten_atlas.py), no error.
    page.select_option("#sample-select", "decimated-knight.off")
    web.wait_for("window.app.state.name === 'decimated-knight.off'")
    web.idle()
    assert page.locator("#flatten").is_enabled()

    # Forms files: not JSON, not forms, and forms that do not fit their faces.
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    page.set_input_files("#forms-file", str(bad))
    web.wait_for("window.app.state.errors.length >= 2")
    assert "Invalid JSON" in page.locator(".toast").first.inner_text()
    bad.write_text(json.dumps({"faces": [[0, 1, 2]]}))
    page.set_input_files("#forms-file", str(bad))
    web.wait_for("window.app.state.errors.length >= 3")
    assert "missing edges, lengths, angles" in page.locator(".toast").first.inner_text()
    bad.write_text(json.dumps({"faces": [[0, 1, 2]], "edges": [[0, 1], [0, 2], [2, 1]],
                               "lengths": [1, 1, 1], "angles": [0, 0, 0]}))
    page.set_input_files("#forms-file", str(bad))
    web.wait_for("window.app.state.errors.length >= 4")
    web.idle()
    text = page.locator(".toast").first.inner_text()
    assert "422" in text and "edges[2]" in text, text
    assert web.app("app.state.name") == "decimated-knight.off"
    png = web.screenshot("05-errors")
    assert_not_blank(png, min_colored=0.0)  # exact forms: the knight is plain grey
    shown = web.shown_errors()
    assert len(shown) == 4 and all(e["title"] and e["detail"] for e in shown)
    # (the 415 comes from the page's worker, whose console Playwright's page does not see)
    assert any("422" in e for e in web.errors)
