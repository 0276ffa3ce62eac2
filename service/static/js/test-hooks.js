// `window.app`: the programmatic interface the browser tests (tests/web) use next to real
// mouse and keyboard input. main.js loads this module only when the page is opened with
// `test` in its query (`/?test`, `/?test&sample=torus.off`): it is not part of the page.

import * as THREE from "three";
import { handleTargets } from "./handles.js";
import { action, busyCount, idle, progressLabel } from "./progress.js";
import { state, store } from "./store.js";
import { toastTiming } from "./toasts.js";

/** Install `window.app` over the page's parts: `page` ({view, mesh, deform, flatten}, filled
 * in as the page starts), its `worker` client, `ready` (start-up done), `startup()` (its
 * stage in words) and `pinned` (the ?transport= of the page). */
export function installTestHooks({ page, worker, ready, startup, pinned }) {
  const change = (id, on) => {
    const input = document.getElementById(id);
    input.checked = on;
    input.dispatchEvent(new Event("change"));
    return idle();
  };
  const project = (x, y, z) => page.view.project(x, y, z);
  window.app = {
    state, ready, idle,
    get toastMs() { return toastTiming.ms; },
    set toastMs(ms) { toastTiming.ms = ms; },
    workerLimits: worker.limits,
    /** What the page is doing, for a test that waited too long. */
    diagnostics: () => ({ startup: startup(), busy: busyCount(), mesh: state.name,
      workerCalls: worker.pending(), progress: progressLabel(),
      errors: state.errors.map((e) => `${e.title}: ${e.detail}`) }),
    get view() { return page.view; },
    /** The API parts the page relies on: its own server has them all; ?transport=deform
     * deforms without sessions. */
    get capabilities() { return { sessions: pinned !== "deform", refine: true, deformRefine: true }; },
    loadSample: (file) => action(page.mesh.loadSample)(file),
    select: (ids) => page.deform.select(ids),
    makeHandle: (ids) => action(page.deform.makeHandle)(ids),
    setActive: (index) => page.deform.setActive(state.handles[index]),
    /** Move (and optionally rotate, axis-angle in radians) the active handle, as the gizmo does. */
    dragHandle(dx, dy, dz, { axis, angle } = {}) {
      const h = state.active;
      if (!h) throw new Error("no active handle");
      page.deform.remember();
      h.pivot.position.add(new THREE.Vector3(dx, dy, dz));
      if (axis) {
        h.pivot.quaternion.premultiply(new THREE.Quaternion()
          .setFromAxisAngle(new THREE.Vector3(...axis).normalize(), angle));
      }
      page.view.request();
      page.deform.onHandleMoved();
      return idle();
    },
    /** The POST /v1/deform body equivalent to the current handles. */
    deformRequest: () => page.deform.deformRequest(),
    handleTargets: () => {
      const { positions, rotations } = handleTargets();
      return { positions: Array.from(positions), rotations };
    },
    vertices: () => Array.from(state.vertices),
    colors: () => Array.from(page.view.mesh.geometry.getAttribute("color").array),
    screenOf: (vertex) => project(...state.vertices.subarray(3 * vertex, 3 * vertex + 3)),
    pivotScreen: () => project(...state.active.pivot.position.toArray()),
    /** Vertices whose normal faces the camera and whose screen position is inside the canvas. */
    visibleVertices() {
      const r = page.view.canvas.getBoundingClientRect();
      return page.view.verticesInRect(r.left, r.top, r.right, r.bottom, { facing: state.closed });
    },
    setRefine: (on) => change("deform-refine", on),
    setOrthonormalize: (on) => change("orthonormalize", on),
    flatten: () => action(page.flatten.flatten)(),
    /** The Blend panel's actions (blend-panel.js). */
    get blend() { return page.blend; },
    downloadGlb: () => action(page.mesh.downloadGlb)(),
    undo: () => action(page.deform.undo)(),
    redo: () => action(page.deform.redo)(),
    setUp: (up) => page.mesh.setUp(up),
    showTab: (tab) => store.set({ tab }),
    setSizeLimits: (sizeLimits) => store.set({ sizeLimits }),
    setColorMode: (colorMode) => store.set({ colorMode }),
    /** Up vector on screen: the screen direction (y down) of the up axis at the mesh centre. */
    screenUp() {
      const view = page.view;
      const c = view.mesh.geometry.boundingSphere.center, u = view.up, r = view.radius * 0.2;
      const a = project(c.x, c.y, c.z), b = project(c.x + r * u.x, c.y + r * u.y, c.z + r * u.z);
      return { x: b.x - a.x, y: b.y - a.y };
    },
  };
}
