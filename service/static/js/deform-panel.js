// The Deform panel: selecting vertices, making handles of them and dragging those with the
// gizmo; the shape follows live through the drag loop (drag-loop.js), its distortion
// against the loaded shape drawn as a histogram and on the mesh; undo and redo.

import { ApiError } from "./api.js";
import { deformBody } from "./deform.js";
import { DragLoop } from "./drag-loop.js";
import { deg, pct, setStats } from "./format.js";
import { handleSetDocument, HandleFileError, handlesFromDocument } from "./handle-files.js";
import { bake, handleTargets, newHandle, setupFor } from "./handles.js";
import { createHistory } from "./history.js";
import { distortion, forms as meshForms, histogram } from "./mesh.js";
import { action, onFileChosen, track, withProgress } from "./progress.js";
import { state, store } from "./store.js";
import { showError } from "./toasts.js";

const $ = (id) => document.getElementById(id);

function drawHistogram(s) {
  const canvas = $("histogram");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const d = s.distortion;
  if (!d) {
    ctx.fillStyle = "#9aa5b1";
    ctx.font = "22px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.fillText("Drag a handle to see the distortion", canvas.width / 2, canvas.height / 2);
    setStats("distortion-stats", []);
    return;
  }
  const length = s.distortionKind === "length";
  const { counts, top } = histogram(length ? d.length : d.angle, 20);
  const W = canvas.width, H = canvas.height, pad = { l: 12, r: 12, t: 14, b: 34 };
  const maxCount = Math.max(...counts, 1);
  const bw = (W - pad.l - pad.r) / counts.length;
  counts.forEach((c, i) => {
    const h = ((H - pad.t - pad.b) * Math.sqrt(c)) / Math.sqrt(maxCount);
    ctx.fillStyle = "#1f7a76";
    ctx.fillRect(pad.l + i * bw + 1, H - pad.b - h, bw - 2, h);
  });
  ctx.strokeStyle = "#9aa5b1";
  ctx.beginPath();
  ctx.moveTo(pad.l, H - pad.b + 0.5);
  ctx.lineTo(W - pad.r, H - pad.b + 0.5);
  ctx.stroke();
  ctx.fillStyle = "#616e7c";
  ctx.font = "20px system-ui, sans-serif";
  ctx.textAlign = "left";
  ctx.fillText("0", pad.l, H - 8);
  ctx.textAlign = "right";
  const f = length ? pct : deg;
  ctx.fillText(f(top), W - pad.r, H - 8);
  ctx.textAlign = "center";
  ctx.fillText(`edges per bin (√ scale, max ${maxCount})`, W / 2, H - 8);
  const sum = length ? d.lengthSummary : d.angleSummary;
  setStats("distortion-stats", [["Mean", f(sum.mean)], ["RMS", f(sum.rms)],
    ["95th percentile", f(sum.p95)], ["Max", f(sum.max)]]);
}

/** What the live updates run on, in words (the technical label stays in state.transport). */
function drawTransport(s) {
  const t = s.transport;
  let text = null;
  if (!s.handles.length) text = s.topo ? "No handles yet." : "";
  else if (s.handles.length === 1) text = "One handle moves the mesh rigidly: add a second one to anchor it.";
  else if (t) {
    const how = t.kind === "session" ? "set up once for these handles"
      : "each drag solved from scratch (slower)";
    const last = s.lastSolveMs !== null ? `, ${s.lastSolveMs.toFixed(0)} ms per update` : "";
    text = `Live: ${how}${last}.`;
  } else text = "Setting up the live deformation for these handles…";  // not the old timing
  if (text !== null) $("transport").textContent = text;
}

function handleItem(h, active, { onSelect, onRemove }) {
  const li = document.createElement("li");
  li.className = h === active ? "active" : "";
  const swatch = document.createElement("span");
  swatch.className = "swatch";
  swatch.style.background = `#${h.color.toString(16).padStart(6, "0")}`;
  const name = document.createElement("span");
  name.className = "name";
  name.textContent = `Handle ${h.id} · ${h.vertices.length} ${h.vertices.length > 1 ? "vertices" : "vertex"}`
    + (h === active ? " · active" : "");
  const remove = document.createElement("button");
  remove.type = "button";
  remove.textContent = "Remove";
  remove.addEventListener("click", (event) => {
    event.stopPropagation();
    onRemove(h);
  });
  li.append(swatch, name, remove);
  li.addEventListener("click", () => onSelect(h));
  return li;
}

/** The Deform panel over the 3D `view`; `pinned` is the ?transport= of the page. */
export function installDeformPanel({ view, pinned }) {
  const loop = new DragLoop({ setup: setupFor, targets: handleTargets, onShape: applyShape,
    onSolved: () => history.refitIfOutgrown(), track, onError: showError, pinned,
    preparing: (fn) => withProgress("Preparing the deformation (factorization)…", fn) });
  const history = createHistory({ view, loop });
  const inScene = new Set();  // the pivots added to the scene

  function applyShape(vertices, { deformed = true } = {}) {
    const t0 = performance.now();
    view.updatePositions(vertices);
    const colorMode = state.colorMode === "checker" ? "checker" : "distortion";
    store.set({ vertices, deformed, colorMode,
      distortion: distortion(state.reference, meshForms(vertices, state.faces, state.topo),
        state.topo) });
    store.set({ lastApplyMs: performance.now() - t0 });
  }

  const setActive = (handle) => store.set({ active: handle });

  function select(ids, { toggle = false } = {}) {
    const used = new Set(state.handles.flatMap((h) => h.vertices));
    const current = new Set(state.selection);
    for (const v of ids) {
      if (used.has(v)) continue;
      if (toggle && current.has(v)) current.delete(v);
      else current.add(v);
    }
    store.set({ selection: [...current] });
  }

  async function makeHandle(ids = state.selection) {
    const used = new Set(state.handles.flatMap((h) => h.vertices));
    const vertices = [...new Set(ids)].filter((v) => !used.has(v));
    if (!vertices.length) throw new ApiError({ title: "Nothing to make a handle of",
      detail: "select vertices that are not already in a handle" });
    history.remember();
    if (state.deformed) store.set({ rest: bake(), deformed: false });
    const handle = newHandle(vertices);
    store.set({ handles: [...state.handles, handle], active: handle,
      selection: state.selection.filter((v) => !vertices.includes(v)) });
    await loop.open();
  }

  async function removeHandle(handle) {
    history.remember();
    if (state.deformed) store.set({ rest: bake(), deformed: false });
    const handles = state.handles.filter((h) => h !== handle);
    store.set({ handles, active: handles.at(-1) ?? null });
    await loop.open();
  }

  async function removeHandles() {
    history.remember();
    store.set({ handles: [], active: null, rest: state.vertices.slice(), deformed: false });
  }

  async function resetShape() {
    history.remember();
    for (const h of state.handles) {
      h.pivot.position.copy(h.center);
      h.pivot.quaternion.identity();
    }
    view.request();
    if (state.transport) loop.request();
  }

  function onHandleMoved() {
    if (state.transport) loop.request();
  }

  /** Download the handles as JSON (the file `ffs deform --handles` reads); its text. */
  function exportHandles() {
    const text = JSON.stringify(handleSetDocument(), null, 1);
    const url = URL.createObjectURL(new Blob([text], { type: "application/json" }));
    const a = document.createElement("a");
    a.href = url;
    a.download = `${(state.name || "mesh").replace(/\.[^.]*$/, "")}-handles.json`;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    return text;
  }

  /** Replace the handles by those of a handle-set document (Export handles' or ffs's JSON),
   * moved to its targets. */
  async function importHandles(doc) {
    let handles;
    try {
      handles = handlesFromDocument(doc);
    } catch (err) {
      if (err instanceof HandleFileError) {
        throw new ApiError({ title: "Not a handle set", detail: err.message });
      }
      throw err;
    }
    history.remember();
    if (state.deformed) store.set({ rest: bake(), deformed: false });
    store.set({ handles, active: handles.at(-1) ?? null, selection: [] });
    await loop.open();
  }

  async function importHandlesFile(file) {
    let doc;
    try {
      doc = JSON.parse(await file.text());
    } catch (err) {
      throw new ApiError({ title: "Not a handle set", detail: `${file.name}: not JSON (${err.message})` });
    }
    await importHandles(doc);
  }

  /** The pivots in the scene are the handles' (the gizmo holds the active one, on this tab);
   * no handles, no deformation. */
  function syncHandles(s) {
    for (const pivot of inScene) {
      if (!s.handles.some((h) => h.pivot === pivot)) {
        view.scene.remove(pivot);
        inScene.delete(pivot);
      }
    }
    for (const h of s.handles) {
      if (!inScene.has(h.pivot)) {
        view.scene.add(h.pivot);
        inScene.add(h.pivot);
      }
    }
    if (!s.handles.length) loop.close();
  }

  function drawHandles(s) {
    const list = $("handle-list");
    list.replaceChildren(...s.handles.map((h) => handleItem(h, s.active, { onSelect: setActive,
      onRemove: action(removeHandle) })));
    $("selection-count").textContent = `${s.selection.length} selected`;
    $("make-handle").disabled = !s.selection.length;
    $("reset-shape").disabled = !s.handles.length;
    $("remove-handles").disabled = !s.handles.length;
    $("export-handles").disabled = !s.handles.length;
  }

  store.subscribe(["handles"], syncHandles);
  store.subscribe(["tab", "active"], (s) => view.attachGizmo(s.tab === "deform"
    && s.active ? s.active.pivot : null));  // the gizmo is a Deform tool: drawn only there
  store.subscribe(["handles", "active", "selection"], drawHandles);
  store.subscribe(["vertices", "selection", "handles"], (s) => {
    if (s.vertices) view.setMarkers(s.vertices, s.selection, s.handles);
  });
  store.subscribe(["undo", "redo"], (s) => {
    $("undo").disabled = !s.undo.length;
    $("redo").disabled = !s.redo.length;
  });
  store.subscribe(["topo", "handles", "transport", "lastSolveMs"], drawTransport);
  store.subscribe(["distortion", "distortionKind"], drawHistogram);

  view.gizmo.addEventListener("mouseDown", () => history.remember());
  view.gizmo.addEventListener("dragging-changed", (event) => event.value || history.refitIfOutgrown());
  view.gizmo.addEventListener("objectChange", onHandleMoved);
  $("make-handle").addEventListener("click", action(() => makeHandle()));
  $("clear-selection").addEventListener("click", () => store.set({ selection: [] }));
  $("reset-shape").addEventListener("click", action(resetShape));
  $("remove-handles").addEventListener("click", action(removeHandles));
  $("export-handles").addEventListener("click", () => exportHandles());
  onFileChosen($("handles-file"), importHandlesFile);
  $("undo").addEventListener("click", action(history.undo));
  $("redo").addEventListener("click", action(history.redo));
  $("deform-refine").checked = state.refineDrags;
  for (const [id, key] of [["orthonormalize", "orthonormalize"], ["deform-refine", "refineDrags"]]) {
    $(id).addEventListener("change", action(async (event) => {
      store.set({ [key]: event.target.checked });
      if (state.handles.length) await loop.open();
    }));
  }
  for (const input of document.querySelectorAll('input[name="distortion-kind"]')) {
    input.addEventListener("change", () => store.set({ distortionKind: input.value,
      ...(state.distortion ? { colorMode: "distortion" } : {}) }));
  }
  for (const input of document.querySelectorAll('input[name="gizmo-mode"]')) {
    input.addEventListener("change", () => view.gizmo.setMode(input.value));
  }
  window.addEventListener("pagehide", () => loop.close({ unloading: true }));

  return {
    loop, select, setActive, makeHandle, removeHandle, resetShape, onHandleMoved, undo: history.undo,
    exportHandles, importHandles,
    redo: history.redo, remember: history.remember,
    /** The POST /v1/deform body equivalent to the current handles. */
    deformRequest() {
      const setup = setupFor();  // first: it groups the faces that the rotations turn
      const { positions, rotations } = handleTargets();
      return deformBody(setup, positions, rotations);
    },
  };
}
