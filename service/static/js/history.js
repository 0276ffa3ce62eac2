// Undo and redo of the Deform panel. A step is a drag, a reset, or adding/removing handles.
// Each keeps what it started from: the rest shape, the shown vertices and every handle's
// vertices and pose. Undo puts that back (no solve: the vertices are the ones shown then)
// and reopens the deformation only when the rest shape or the handle set differ from the
// open one. After a step, a shape that was on screen and grew out of it is fitted again.

import { state, store } from "./store.js";

const HISTORY_LIMIT = 50;

function snapshot() {
  return {
    rest: state.rest, vertices: state.vertices, deformed: state.deformed, active: state.active,
    distortion: state.distortion,
    handles: state.handles.map((h) => ({ handle: h, vertices: h.vertices, start: h.start,
      center: h.center.clone(), position: h.pivot.position.clone(),
      quaternion: h.pivot.quaternion.clone() })),
  };
}

/** Undo/redo over the 3D `view` and the deformation's DragLoop `loop`. */
export function createHistory({ view, loop }) {
  /** Whether the whole shape is on screen, below the view's toolbar (`toolbar`) or
   * anywhere on the canvas. */
  function shapeInView({ toolbar = true } = {}) {
    const canvas = view.canvas.getBoundingClientRect();
    const bar = document.getElementById("view-toolbar").getBoundingClientRect();
    return view.fits(state.vertices, { top: toolbar ? Math.max(0, bar.bottom - canvas.top) : 0 });
  }

  /** After a step (once the gizmo is let go): a shape that was on screen and grew out of
   * it, or under the toolbar, is fitted again from the same direction. */
  function refitIfOutgrown() {
    if (!state.vertices || view.gizmo.dragging || !state.inViewBefore) return;
    if (!shapeInView()) {
      view.frame({ keep: true });
      store.set({ inViewBefore: shapeInView({ toolbar: false }) });
    }
  }

  /** A step begins: keep what it starts from. */
  function remember() {
    if (!state.vertices) return;
    store.set({ inViewBefore: shapeInView({ toolbar: false }),
      undo: [...state.undo, snapshot()].slice(-HISTORY_LIMIT), redo: [] });
  }

  async function restore(snap) {
    const handles = snap.handles.map((s) => {
      const h = s.handle;
      Object.assign(h, { vertices: s.vertices, start: s.start });
      h.center.copy(s.center);
      h.pivot.position.copy(s.position);
      h.pivot.quaternion.copy(s.quaternion);
      return h;
    });
    view.updatePositions(snap.vertices);
    store.set({ handles, rest: snap.rest, vertices: snap.vertices, deformed: snap.deformed,
      distortion: snap.distortion,
      active: handles.includes(snap.active) ? snap.active : handles.at(-1) ?? null });
    if (!loop.current()) {
      if (handles.length) await loop.open({ solve: false });
      else loop.close();
    }
  }

  // Take the newest snapshot of one stack, keep the current state on the other.
  async function travel(from, to) {
    if (loop.solving) await loop.solving;
    const snap = state[from].at(-1);
    if (!snap) return;
    store.set({ [from]: state[from].slice(0, -1), [to]: [...state[to], snapshot()] });
    await restore(snap);
  }

  return {
    remember, refitIfOutgrown,
    undo: () => travel("undo", "redo"),
    redo: () => travel("redo", "undo"),
  };
}
