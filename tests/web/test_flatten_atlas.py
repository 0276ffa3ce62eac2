"""The Flatten tab on a closed mesh (issue 41): the knight is cut into charts, the packed
layout is shown beside the 3D view, and the 3D view carries the atlas's checkerboard on a
copy of the mesh with its seam vertices duplicated."""

from __future__ import annotations

import httpx
import numpy as np

from tests.helpers.web import assert_not_blank


def test_flatten_tab_on_a_closed_mesh_shows_the_atlas(web):
    page = web.open()
    page.select_option("#sample-select", "decimated-knight.off")
    web.wait_for("window.app.state.name === 'decimated-knight.off'")
    web.idle()
    assert web.app("app.state.closed") is True
    page.keyboard.press("3")  # the Flatten tab
    assert page.locator("#flatten").is_enabled()
    page.click("#flatten")
    web.wait_for("window.app.state.flat !== null", timeout=120)
    web.idle()
    assert page.locator("#view-flat").is_visible()
    stats = page.locator("#flatten-stats").inner_text()
    charts = web.app("app.state.flat.report.atlas.charts")
    assert charts >= 2 and f"Charts\n{charts}" in stats.replace("\t", "\n"), stats
    assert "Packing efficiency" in stats and "Flipped faces\n0" in stats.replace("\t", "\n")

    # The page's atlas is the API's for the same mesh.
    vertices = np.asarray(web.app("app.vertices()")).reshape(-1, 3)
    faces = np.asarray(web.app("Array.from(app.state.faces)")).reshape(-1, 3)
    with httpx.Client(base_url=web.base, timeout=120) as api:
        want = api.post("/v1/parameterize", json={
            "vertices": vertices.tolist(), "faces": faces.tolist(),
            "options": {"orthonormalize": True}}).json()
    assert want["report"]["atlas"]["charts"] == charts
    uv_faces = np.asarray(web.app("Array.from(app.state.flat.atlas.uvFaces)")).reshape(-1, 3)
    np.testing.assert_array_equal(uv_faces, np.asarray(want["uv_faces"]))

    # The 3D view: the mesh is replaced by its atlas copy, textured, one vertex per uv.
    overlay = web.app("""(() => { const m = app.view.scene.getObjectByName('atlas');
        return m && {visible: m.visible, count: m.geometry.getAttribute('position').count,
                     uv: m.geometry.getAttribute('uv') !== undefined,
                     map: m.material.map !== null, meshHidden: !app.view.mesh.visible}; })()""")
    assert overlay == {"visible": True, "count": len(want["uv_vertex"]), "uv": True,
                       "map": True, "meshHidden": True}
    assert web.app("app.state.colorMode") == "checker"
    assert_not_blank(page.locator("#view-3d canvas").screenshot())
    assert_not_blank(page.locator("#view-flat canvas").screenshot(), min_colored=0.05)
    web.screenshot("41-flatten-closed-atlas")

    # Another colour mode gives the plain mesh back.
    page.select_option("#color-mode", "plain")
    web.idle()
    assert web.app("app.view.scene.getObjectByName('atlas') === undefined")
    assert web.app("app.view.mesh.visible") is True
    assert web.shown_errors() == []
