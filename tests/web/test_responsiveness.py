"""Large meshes in the page: what the main thread does while a 100K-face mesh loads (the
browser's long-task timing), what a drag costs the page on top of the server at 20K faces,
and that updates never compile a shader. Timings are measured and written to
tests/artifacts/web/responsiveness.json (the suite never asserts a speed: the machine is
shared); what is asserted is structural (no shader compiled by an update, the mesh shown).

The big meshes come from ../shared/meshes beside the repository (as in CI); without them
those tests are skipped.
"""

from __future__ import annotations

import json

import pytest

from tests.helpers import REPO
from tests.helpers.web import ARTIFACTS

SHARED = REPO.parent / "shared" / "meshes"
RESULTS = ARTIFACTS / "responsiveness.json"

# Long tasks (> 50 ms on the main thread) and the shaders compiled, counted from the start.
PROBES = """
window.__longTasks = [];
new PerformanceObserver((list) => {
  for (const e of list.getEntries()) window.__longTasks.push(Math.round(e.duration));
}).observe({ type: "longtask", buffered: true });
window.__shaders = 0;
for (const proto of [WebGLRenderingContext.prototype, WebGL2RenderingContext.prototype]) {
  const compile = proto.compileShader;
  proto.compileShader = function (shader) {
    window.__shaders++;
    return compile.call(this, shader);
  };
}
"""


def _record(key: str, value: dict) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    data = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    data[key] = value
    RESULTS.write_text(json.dumps(data, indent=2) + "\n")
    print(key, value)


def _shared(name: str):
    path = SHARED / name
    if not path.is_file():
        pytest.skip(f"{path} is not there (CI has ../shared beside the repository)")
    return path


def test_updates_compile_no_shader(web):
    """Selections, new handles, drags and colour refreshes reuse their materials: once the
    first drag has been drawn, nothing compiles a shader any more (the marker spheres used to
    be rebuilt with new materials on every update). In the Deform tab, where the handles'
    gizmo is drawn."""
    web.page.add_init_script(PROBES)
    page = web.open()
    page.click("#tab-deform")
    web.app("app.makeHandle([0, 1, 2])")
    web.app("app.makeHandle(app.visibleVertices().slice(600, 620))")
    web.app("app.dragHandle(0, 0, 5)")
    web.frame()
    compiled = page.evaluate("window.__shaders")
    assert compiled > 0  # the probe sees the page's shaders
    for k in range(4):
        web.app("app.dragHandle(1, -1, 2)")
        web.app("app.select(app.visibleVertices().slice(300 + 10 * arg, 310 + 10 * arg))", k)
        web.frame()
    web.app("app.makeHandle(app.visibleVertices().slice(900, 905))")
    web.app("app.dragHandle(0, 3, 0)")
    page.click("#tab-deform")
    page.locator("#panel-deform label", has_text="Dihedral").click()
    web.frame()
    assert page.evaluate("window.__shaders") == compiled
    assert web.shown_errors() == []


def test_large_mesh_load_main_thread(web):
    """Opening armadillo (86K faces): the page stays responsive (file reading, JSON, topology
    and forms run in a worker). Long tasks are recorded with rendering paused (the page's own
    work) and with rendering (headless SwiftShader draws on the CPU)."""
    path = _shared("armadillo.obj")
    web.page.add_init_script(PROBES)
    page = web.open()
    measured = {}
    for paused in (True, False):
        web.app("(app.view.paused = arg, 0)", paused)
        page.evaluate("window.__longTasks = []")
        started = page.evaluate("performance.now()")
        page.set_input_files("#mesh-file", str(path))
        web.wait_for("window.app.state.name === 'armadillo.obj'"
                     " && window.app.state.vertices.length > 100000", timeout=120)
        shown = page.evaluate("performance.now()") - started
        web.idle()
        reported = page.evaluate("performance.now()") - started
        assert web.app("app.state.integrability.integrable") is True
        assert web.app("app.state.faces.length") == 3 * 86482
        tasks = page.evaluate("window.__longTasks")
        measured["paused" if paused else "rendering"] = {
            "mesh_shown_ms": round(shown), "report_ms": round(reported),
            "long_tasks_ms": tasks, "longest_ms": max(tasks, default=0)}
        page.click("#tab-mesh")
        page.select_option("#sample-select", "face.off")
        web.wait_for("window.app.state.name === 'face.off'")
        web.idle()
    _record("armadillo_load", measured)
    web.app("(app.view.paused = false, 0)")
    assert web.shown_errors() == []


def test_drag_client_cost_20k_faces(web):
    """A drag on rocker-arm (20K faces): the page's own cost per update (positions, normals,
    distortion, colours, markers; rendering paused) next to the round trip of the update."""
    path = _shared("rocker-arm.obj")
    web.open()
    web.load_file(path)
    web.app("app.makeHandle(app.visibleVertices().slice(0, 30))")
    web.app("app.makeHandle(app.visibleVertices().slice(-30))")
    web.app("(app.view.paused = true, 0)")
    client, round_trip = [], []
    for k in range(6):
        web.app("app.dragHandle(0.002, 0.003 * arg, 0.001)", k)
        client.append(web.app("app.state.lastApplyMs"))
        round_trip.append(web.app("app.state.lastSolveMs"))
    web.app("(app.view.paused = false, 0)")
    assert len(client) == 6 and all(c > 0 for c in client)
    client.sort()
    round_trip.sort()
    _record("rocker_arm_drag", {"faces": 20088, "client_ms_sorted": [round(c, 1) for c in client],
                                "update_round_trip_ms_sorted": [round(r) for r in round_trip],
                                "client_median_ms": round(client[3], 1)})
    assert web.shown_errors() == []
