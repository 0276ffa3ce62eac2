// Mouse and keyboard on the page: a click on the mesh selects a vertex, Shift+drag a box of
// them (on closed meshes only those facing the camera), and the keyboard shortcuts listed
// in the help overlay (index.html). What they do is the panels': `actions` names it.

import { action } from "./progress.js";
import { state, store } from "./store.js";

const $ = (id) => document.getElementById(id);
/** The tabs in order, from the one place they are declared: index.html's tab list (a
 * `role="tab"` button `tab-<name>` per tab, controlling `panel-<name>`; key N picks the Nth). */
export const tabs = () => [...document.querySelectorAll('[role="tab"]')].map((button) => ({
  name: button.id.replace(/^tab-/, ""), label: button.firstChild.textContent.trim() }));
const UP_AXES = ["+y", "+z", "+x", "-y", "-z", "-x"];

function setHelp(open) {
  $("help").hidden = !open;
  if (open) $("help-close").focus();
}

function kbd(text) {
  const key = document.createElement("kbd");
  key.textContent = text;
  return key;
}

function toggleCheckbox(id) {
  $(id).checked = !$(id).checked;
  $(id).dispatchEvent(new Event("change"));
}

/** Tabs, the help overlay, selection with the mouse on `view`'s canvas, and the keyboard
 * shortcuts. `actions`: {select, makeHandle, removeHandle, undo, redo, setUp}. */
export function installInput({ view, actions }) {
  const names = tabs().map((tab) => tab.name);
  store.subscribe(["tab"], (s) => {
    for (const tab of names) {
      $(`tab-${tab}`).setAttribute("aria-selected", String(tab === s.tab));
      $(`panel-${tab}`).hidden = tab !== s.tab;
    }
  });
  for (const tab of names) $(`tab-${tab}`).addEventListener("click", () => store.set({ tab }));
  $("help-tab-keys").replaceChildren(kbd("1"), "–", kbd(String(names.length)));
  $("help-tabs").textContent = `${tabs().map((tab) => tab.label).join(", ")} tab`;
  $("help-open").addEventListener("click", () => setHelp(true));
  $("help-close").addEventListener("click", () => setHelp(false));
  $("help").addEventListener("click", (event) => {
    if (event.target === $("help")) setHelp(false);
  });

  const canvas = view.canvas, box = $("selection-box");
  let down = null;
  canvas.addEventListener("pointerdown", (event) => {
    if (event.button !== 0 || !state.vertices) return;
    down = { x: event.clientX, y: event.clientY, shift: event.shiftKey,
      gizmo: view.gizmoActive() };
    if (down.shift && !down.gizmo) {
      view.controls.enabled = false;
      Object.assign(box.style, { left: `${down.x}px`, top: `${down.y}px`, width: "0px", height: "0px" });
      box.hidden = false;
    }
  });
  window.addEventListener("pointermove", (event) => {
    if (!down?.shift || down.gizmo) return;
    const left = Math.min(down.x, event.clientX), top = Math.min(down.y, event.clientY);
    Object.assign(box.style, { left: `${left}px`, top: `${top}px`,
      width: `${Math.abs(event.clientX - down.x)}px`, height: `${Math.abs(event.clientY - down.y)}px` });
  });
  window.addEventListener("pointerup", (event) => {
    if (!down) return;
    const start = down;
    down = null;
    if (start.shift && !start.gizmo) {
      box.hidden = true;
      view.controls.enabled = true;
      const ids = view.verticesInRect(Math.min(start.x, event.clientX), Math.min(start.y, event.clientY),
        Math.max(start.x, event.clientX), Math.max(start.y, event.clientY),
        { facing: state.closed });
      actions.select(ids);
      if (ids.length) store.set({ tab: "deform" });
      return;
    }
    const moved = Math.hypot(event.clientX - start.x, event.clientY - start.y);
    if (moved < 5 && !start.gizmo && event.target === canvas) {
      const v = view.pickVertex(event.clientX, event.clientY);
      if (v >= 0) {
        actions.select([v], { toggle: true });
        store.set({ tab: "deform" });
      }
    }
  });

  window.addEventListener("keydown", (event) => {
    // Typing in a field is not a shortcut (a focused checkbox or button does not count).
    const field = event.target.closest?.("select, textarea, input");
    if (field && !(field.tagName === "INPUT" && ["checkbox", "radio", "file", "button"].includes(field.type))) return;
    const key = event.key, ctrl = event.ctrlKey || event.metaKey;
    if (key === "?") {
      setHelp($("help").hidden);
    } else if (key === "Escape") {
      if (!$("help").hidden) setHelp(false);
      else store.set({ selection: [] });
    } else if (ctrl && (key === "z" || key === "Z")) {
      event.preventDefault();
      action(event.shiftKey ? actions.redo : actions.undo)();
    } else if (ctrl && key === "y") {
      event.preventDefault();
      action(actions.redo)();
    } else if (ctrl || event.altKey) {
      return;
    } else if (key >= "1" && key <= String(names.length)) {
      store.set({ tab: names[Number(key) - 1] });
    } else if (key === "w" || key === "e") {
      const mode = key === "w" ? "translate" : "rotate";
      document.querySelector(`input[name="gizmo-mode"][value="${mode}"]`).checked = true;
      view.gizmo.setMode(mode);
    } else if ((key === "Delete" || key === "Backspace") && state.active) {
      action(actions.removeHandle)(state.active);
    } else if (key === "h" && state.selection.length) {
      action(actions.makeHandle)();
    } else if (key === "f" && state.vertices) {
      view.frame({ keep: true });
    } else if (key === "r" && state.vertices) {
      view.frame();
    } else if (key === "g") {
      toggleCheckbox("grid-toggle");
    } else if (key === "m") {
      toggleCheckbox("wireframe");
    } else if (key === "u" && state.vertices) {
      actions.setUp(UP_AXES[(UP_AXES.indexOf(state.up) + 1) % UP_AXES.length]);
    }
  });
}
