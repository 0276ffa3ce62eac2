// The page: state, tabs, panels, interaction, undo/redo, and `window.app` (a small
// programmatic API that the browser tests use next to real mouse input). Everything the page
// knows comes from the service's public HTTP API; errors are shown as toasts with the problem
// document's text (they close by themselves and an identical one is not repeated).

import * as THREE from "three";
import * as api from "./api.js";
import { CSS_GRADIENT, scaleFor, uniformColors, vertexColors } from "./colormap.js";
import { DeformTransport, SessionTransport, deformBody } from "./deform.js";
import {
  bounds, distortion, facesAround, flatten3, forms as meshForms, histogram, prepareMesh, rigidAlign,
  rows3,
} from "./mesh.js";
import { FlatView, MeshView, axisVector } from "./viewer.js";
import { WorkerClient } from "./worker-client.js";

const $ = (id) => document.getElementById(id);
const HANDLE_COLORS = [0xe4572e, 0x2e86ab, 0x9c27b0, 0xff9f1c, 0x43aa8b, 0xd81159];
const DEFECT_LABELS = { vertex_defect: "Total", gauss_defect: "Gauss", codazzi_defect: "Codazzi" };
const UP_AXES = ["+y", "+z", "+x", "-y", "-z", "-x"];
const TABS = ["mesh", "deform", "flatten", "forms"];
// Changes below these are round-off (float32 vertices over the wire): the distortion map
// stays dark instead of stretching them over the whole ramp.
const LENGTH_FLOOR = 1e-3;                // 0.1 %
const ANGLE_FLOOR = (0.1 * Math.PI) / 180; // 0.1°
const ROUND_OFF = 1e-12;                   // a max defect below this is floating-point noise
const HISTORY_LIMIT = 50;

const state = {
  name: null,
  source: null,
  vertices: null,      // Float64Array(3n): what is shown
  faces: null,         // Uint32Array(3m)
  topo: null,
  rest: null,          // deformation rest shape (Float64Array)
  reference: null,     // forms of the shape as loaded: the distortion reference
  forms: null,         // forms document of the loaded mesh (or the uploaded forms)
  integrability: null,
  defectPart: "vertex_defect",
  distortion: null,
  distortionKind: "length",
  flat: null,
  colorMode: "plain",
  selection: [],
  handles: [],
  active: null,
  orthonormalize: false,
  refineDrags: true,  // progressive drags: the linear shape at once, settling to the refined
  transport: null,
  deformed: false,
  solving: null,
  solveWanted: false,
  solves: 0,
  lastSolveMs: null,
  lastApplyMs: null,
  errors: [],
  up: "+y",
  upSource: "guess",
  tab: "mesh",
  undo: [],
  redo: [],
  reconstruction: null, // {refined, linear, report, input, showing}
  analysisError: null,
};

let view, flatView, caps = { sessions: false, refine: false };
let samples = [];

// ------------------------------------------------------------------------------ worker
// Reading meshes and the big JSON of forms and reports happen in js/worker.js; every call
// settles (js/worker-client.js bounds the waits and says in words what did not answer).

const worker = new WorkerClient("/static/js/worker.js");
const inWorker = (kind, args, label) => worker.call(kind, args, label);
const TRANSPORT = new URLSearchParams(location.search).get("transport");
let handleCounter = 0;

// ------------------------------------------------------------------------- formatting

function fmt(x, digits = 3) {
  if (x === null || x === undefined || Number.isNaN(x)) return "–";
  const a = Math.abs(x);
  if (a === 0) return "0";
  if (a < 1e-3 || a >= 1e5) return x.toExponential(digits - 1);
  return Number(x.toPrecision(digits)).toString();
}
const pct = (x) => `${(100 * x).toFixed(x < 0.001 ? 3 : 2)} %`;
const deg = (x) => `${((180 / Math.PI) * x).toFixed(2)}°`;

function setStats(id, rows) {
  const dl = $(id);
  dl.replaceChildren();
  for (const [label, value, cls] of rows) {
    const dt = document.createElement("dt"), dd = document.createElement("dd");
    dt.textContent = label;
    if (value instanceof Node) dd.append(value);
    else dd.textContent = value;
    if (cls) dd.className = cls;
    dl.append(dt, dd);
  }
}

/** A number (or short value) that never breaks across lines. */
function num(text) {
  const span = document.createElement("span");
  span.className = "num";
  span.textContent = text;
  return span;
}

function badge(ok, yes = "yes", no = "no") {
  const span = document.createElement("span");
  span.className = `badge ${ok ? "ok" : "bad"}`;
  span.textContent = ok ? yes : no;
  return span;
}

function status(text) {
  $("statusbar").textContent = text;
}

function updateStatus() {
  if (!state.vertices) return status("Ready.");
  const parts = [`${state.name}`, `${state.vertices.length / 3} vertices`,
    `${state.faces.length / 3} faces`];
  if (state.handles.length) parts.push(`${state.handles.length} handle${state.handles.length > 1 ? "s" : ""}`);
  if (state.lastSolveMs !== null) parts.push(`last update ${state.lastSolveMs.toFixed(0)} ms`);
  parts.push(`up: ${state.up.replace("+", "")}${{ guess: " (guessed)", sample: " (sample)" }[state.upSource] ?? ""}`);
  status(parts.join(" · "));
}

// ----------------------------------------------------------------------- busy, errors

let busy = 0;
const idleWaiters = [];
const nextTask = () => new Promise((resolve) => setTimeout(resolve, 0));

function track(promise) {
  busy++;
  return promise.finally(() => {
    busy--;
    if (!busy) idleWaiters.splice(0).forEach((resolve) => resolve());
  });
}

function idle() {
  return busy ? new Promise((resolve) => idleWaiters.push(resolve)) : Promise.resolve();
}

const toastTimers = new WeakMap();

function closeToast(toast) {
  toast.classList.add("fading");
  setTimeout(() => toast.remove(), 300);
}

function scheduleClose(toast) {
  clearTimeout(toastTimers.get(toast));
  toastTimers.set(toast, setTimeout(() => closeToast(toast), window.app?.toastMs ?? 8000));
}

function showError(err) {
  if (err?.name === "AbortError") {
    status("Cancelled.");
    return;
  }
  const info = api.describe(err);
  state.errors.push(info);
  console.warn("[ffs]", info.title, info.detail, err);
  const box = $("toasts");
  const key = `${info.title}\n${info.detail}`;
  const same = [...box.children].find((t) => t.dataset.key === key && !t.classList.contains("fading"));
  if (same) {  // the same message again: count it instead of stacking a copy
    const count = same.querySelector(".toast-count");
    const n = Number(same.dataset.count) + 1;
    same.dataset.count = String(n);
    count.textContent = `×${n}`;
    box.prepend(same);
    scheduleClose(same);
    return;
  }
  const toast = document.createElement("div");
  toast.className = "toast";
  toast.dataset.key = key;
  toast.dataset.count = "1";
  toast.setAttribute("role", "alert");
  const title = document.createElement("div");
  title.className = "toast-title";
  title.textContent = info.title;
  const count = document.createElement("span");
  count.className = "toast-count";
  title.append(count);
  const detail = document.createElement("div");
  detail.className = "toast-detail";
  detail.textContent = info.detail;
  toast.append(title, detail);
  if (info.items.length) {
    const list = document.createElement("ul");
    for (const item of info.items) {
      const li = document.createElement("li");
      li.textContent = item;
      list.append(li);
    }
    toast.append(list);
  }
  if (info.context) {  // which request failed: for developers, folded away
    const more = document.createElement("details");
    const summary = document.createElement("summary");
    summary.textContent = "Technical details";
    const context = document.createElement("div");
    context.className = "toast-context";
    context.textContent = info.context + (info.kind ? ` · ${info.kind}` : "");
    more.append(summary, context);
    toast.append(more);
  }
  const close = document.createElement("button");
  close.className = "toast-close";
  close.type = "button";
  close.setAttribute("aria-label", "Dismiss");
  close.textContent = "×";
  close.addEventListener("click", () => toast.remove());
  toast.append(close);
  toast.addEventListener("mouseenter", () => clearTimeout(toastTimers.get(toast)));
  toast.addEventListener("mouseleave", () => scheduleClose(toast));
  box.prepend(toast);
  scheduleClose(toast);
  while (box.children.length > 4) box.lastChild.remove();
}

/** Run an async UI action: tracked for idle(), errors shown, never thrown away. */
function action(fn) {
  return (...args) => track(Promise.resolve().then(() => fn(...args))).catch(showError);
}

const progress = {
  controller: null,
  start(label, { cancellable = false } = {}) {
    $("progress").hidden = false;
    $("progress").classList.add("indeterminate");
    $("progress-bar").style.width = "";
    $("progress-label").textContent = label;
    this.controller = cancellable ? new AbortController() : null;
    $("progress-cancel").hidden = !cancellable;
    return this.controller?.signal;
  },
  update(fraction, label) {
    $("progress").classList.remove("indeterminate");
    $("progress-bar").style.width = `${Math.round(100 * fraction)}%`;
    $("progress-label").textContent = label;
  },
  done() {
    $("progress").hidden = true;
    this.controller = null;
  },
};

async function withProgress(label, fn, options) {
  const signal = progress.start(label, options);
  try {
    return await fn(signal);
  } finally {
    progress.done();
  }
}

function jobProgress(label) {
  return (job) => {
    const p = job.progress || {};
    const stage = p.stage ? ` · ${p.stage}` : "";
    progress.update(p.fraction ?? 0, `${label}: ${job.status}${stage} · ${Math.round(100 * (p.fraction ?? 0))} %`);
  };
}

// ------------------------------------------------------------------------ colour maps

function setLegend(title, scale, format, maxNote = "") {
  $("legend").hidden = false;
  $("legend-title").textContent = title;
  $("legend-ramp").style.background = CSS_GRADIENT;
  $("legend-min").textContent = format(scale.log ? scale.min : 0);
  $("legend-max").textContent = `${scale.clipped ? "≥ " : ""}${format(scale.max)}${maxNote}`;
}

/** Colour scale of the defect: exact forms on a fixed ramp from round-off to the tolerance
 * (so they stay dark), others from the tolerance up (only what fails lights up). */
function defectScale(r, values) {
  return r.integrable ? scaleFor(values, { log: true, min: 1e-17, max: r.tolerance })
    : scaleFor(values, { log: true, min: r.tolerance });
}

function refreshColors() {
  if (!state.vertices) return;
  const mode = state.colorMode;
  $("color-mode").value = mode;
  view.setTexture(mode === "checker" && state.flat ? state.flat.texcoords : null);
  if (mode === "defect" && state.integrability) {
    const r = state.integrability;
    const values = r[state.defectPart];
    const scale = defectScale(r, values);
    view.setColors(vertexColors(values, scale));
    setLegend(`${DEFECT_LABELS[state.defectPart]} defect per vertex (rad, log scale)`
      + (r.integrable ? ": all below the tolerance" : ""), scale, (x) => fmt(x, 2),
    r.integrable ? " (tolerance)" : "");
  } else if (mode === "distortion" && state.distortion) {
    const length = state.distortionKind === "length";
    const values = length ? state.distortion.vertexLength : state.distortion.vertexAngle;
    const scale = scaleFor(values, { floor: length ? LENGTH_FLOOR : ANGLE_FLOOR });
    view.setColors(vertexColors(values, scale));
    setLegend((length ? "Edge-length change (max per vertex)" : "Dihedral-angle change (max per vertex)")
      + (scale.quiet ? ": none" : ""), scale, length ? pct : deg);
  } else if (mode === "checker" && state.flat) {
    view.setColors(uniformColors(state.vertices.length / 3, [255, 255, 255]));
    $("legend").hidden = true;
  } else {
    state.colorMode = "plain";
    $("color-mode").value = "plain";
    view.setColors(null);
    $("legend").hidden = true;
  }
}

function setColorMode(mode) {
  state.colorMode = mode;
  refreshColors();
}

function enableColorOptions() {
  const options = $("color-mode").options;
  for (const option of options) {
    option.disabled = { plain: false, defect: !state.integrability,
      distortion: !state.distortion, checker: !state.flat }[option.value];
  }
}

// ----------------------------------------------------------------------- tabs, view

function showTab(name) {
  state.tab = name;
  for (const tab of TABS) {
    $(`tab-${tab}`).setAttribute("aria-selected", String(tab === name));
    $(`panel-${tab}`).hidden = tab !== name;
  }
  // The handles' gizmo is a Deform tool: drawn (and grabbable) only there.
  if (view) view.attachGizmo(name === "deform" && state.active ? state.active.pivot : null);
}

/** The up axis of a mesh: the sample's known orientation, else a guess from the bounding
 * box (Z when the mesh is clearly taller in Z than in Y, as scans and CAD files are; Y,
 * the OBJ/glTF convention, otherwise). */
function guessUp(vertices, sampleUp) {
  if (sampleUp) return { up: sampleUp, source: "sample" };
  const { min, max } = bounds(vertices);
  return { up: max[2] - min[2] > 1.15 * (max[1] - min[1]) ? "+z" : "+y", source: "guess" };
}

function setUp(up, source = "user") {
  state.up = up;
  state.upSource = source;
  $("up-axis").value = up;
  view.setUp(axisVector(up));
  updateStatus();
}

// ---------------------------------------------------------------------------- loading

function renderMeshStats() {
  const n = state.vertices.length / 3, m = state.faces.length / 3;
  const E = state.topo.edges.length / 2;
  const { min, max } = bounds(state.vertices);
  const boundary = state.boundaryEdges;
  setStats("mesh-stats", [
    ["Vertices · faces", num(`${n.toLocaleString("en")} · ${m.toLocaleString("en")}`)],
    ["Edges", num(`${E.toLocaleString("en")}${boundary ? ` (${boundary.toLocaleString("en")} on the boundary)`
      : " (closed)"}`)],
    ["Size", num(max.map((x, k) => fmt(x - min[k])).join(" × "))],
    ["Mean edge", num(fmt(state.meanEdge))],
  ]);
}

/** Show a mesh (prepared by mesh.prepareMesh, or {vertices, faces} as nested arrays) and
 * analyse it. */
async function openMesh(mesh, name, source, extra = {}) {
  const p = mesh.topo ? mesh : prepareMesh(mesh.vertices, mesh.faces);
  closeTransport();
  for (const h of state.handles) view.scene.remove(h.pivot);
  view.attachGizmo(null);
  Object.assign(state, {
    name, source, vertices: p.vertices, faces: p.faces, topo: p.topo, reference: p.reference,
    meanEdge: p.meanEdge, boundaryEdges: p.boundaryEdges, rest: p.vertices.slice(),
    handles: [], active: null, selection: [], deformed: false, distortion: null, flat: null,
    integrability: null, forms: null, lastSolveMs: null, solves: 0, undo: [], redo: [],
    analysisError: null, reconstruction: extra.reconstruction ?? null,
  });
  state.closed = state.boundaryEdges === 0;
  const { up, source: upSource } = extra.up ? { up: extra.up, source: extra.upSource ?? "user" }
    : guessUp(state.vertices, extra.sampleUp);
  state.up = up;
  state.upSource = upSource;
  $("up-axis").value = up;
  view.setUp(axisVector(up), { refit: false });
  view.setMesh(state.vertices, state.faces, state.topo.edges);
  await nextTask();  // a big mesh: let the page breathe between building and panels
  $("empty-state").hidden = true;
  $("mesh-title").textContent = `${name}${source === "sample" ? " (sample)" : ""}`;
  showSampleChoice();
  hideFlat();
  renderMeshStats();
  renderHandles();
  renderDistortion();
  renderReconstruction();
  setStats("flatten-stats", []);
  $("download-glb").disabled = false;
  $("flatten").disabled = state.closed;
  $("flatten-note").textContent = state.closed
    ? "This mesh is closed: a flat layout needs a boundary. Open a mesh with a hole (the Face "
      + "sample is a disk)." : "";
  $("bend-forms").disabled = true;  // until the forms are known
  state.colorMode = "plain";
  enableColorOptions();
  renderIntegrability();  // "computing…": never the previous mesh's report
  refreshColors();
  updateStatus();
  await analyze(extra);
}

let analysisRun = 0;

/** The integrability report of the shown mesh (or of the given forms, when they are what
 * was loaded), into the Mesh panel. */
async function analyze({ forms, integrability } = {}) {
  const run = ++analysisRun;
  try {
    const result = await withProgress("Integrability report…", async () => (forms && integrability
      ? { forms, integrability } : inWorker("analyze", { vertices: state.vertices,
        faces: state.faces }, "computing the integrability report")));
    if (run !== analysisRun) return;  // another mesh (or answer) was shown meanwhile
    state.forms = result.forms;
    state.integrability = result.integrability;
  } catch (err) {
    if (run !== analysisRun) throw err;
    state.forms = state.integrability = null;
    state.analysisError = err?.name === "AbortError" ? null : api.describe(err);
    renderIntegrability();
    throw err;
  }
  renderIntegrability();
  enableColorOptions();
  $("bend-forms").disabled = false;
  // Colours only where there is something to see: exact forms are plain.
  setColorMode(state.integrability.integrable ? "plain" : "defect");
}

const maxOf = (values) => values.reduce((a, b) => Math.max(a, Math.abs(b)), 0);

/** The global loops of a report in words: how many pass, and the worst of each kind with
 * its unit (a rotation in radians, a translation in mean edge lengths: report.max_defect
 * mixes the two with the vertex defects, so the page never shows it bare). */
function loopsText(r) {
  const { rotation, translation } = r.global_holonomy;
  const loops = [...rotation, ...translation];
  if (!loops.length) return "none";
  const worst = (list) => list.reduce((a, l) => Math.max(a, l.magnitude), 0);
  const failing = [];
  if (worst(rotation) > r.tolerance) failing.push(`rotation ${fmt(worst(rotation), 3)} rad`);
  if (worst(translation) > r.tolerance) {
    failing.push(`translation ${fmt(worst(translation), 3)} mean edge lengths`);
  }
  return `${loops.filter((l) => l.passes).length} / ${loops.length} pass`
    + (failing.length ? ` (worst: ${failing.join(", ")})` : "");
}

function integrabilityVerdict(r) {
  const loops = [...r.global_holonomy.rotation, ...r.global_holonomy.translation];
  const failingLoops = loops.filter((l) => !l.passes).length;
  const vertexMax = maxOf(r.vertex_defect);
  if (r.integrable && r.max_defect < ROUND_OFF) {
    return [true, `Forms are exact (defect ${fmt(r.max_defect, 2)}, round-off).`];
  }
  if (r.integrable) {
    return [true, `Forms are integrable (vertex defects up to ${fmt(vertexMax, 2)} rad, below `
      + `the tolerance ${fmt(r.tolerance, 1)}).`];
  }
  const parts = [];
  if (r.failing_vertices.length) {
    parts.push(`vertex defects up to ${fmt(vertexMax, 2)} rad (${r.failing_vertices.length} `
      + "vertices above the tolerance)");
  }
  if (failingLoops) parts.push(`${failingLoops} global loop${failingLoops > 1 ? "s" : ""} fail`);
  if (r.triangle_violations.length) {
    parts.push(`${r.triangle_violations.length} faces break the triangle inequality`);
  }
  return [false, `Not integrable: ${parts.join("; ") || "see the details"}.`];
}

function renderIntegrability() {
  const r = state.integrability;
  const verdict = $("integrability-summary");
  $("show-defect").disabled = !r;
  if (!r) {
    const failed = state.analysisError;
    verdict.className = failed ? "verdict bad" : "verdict";
    verdict.textContent = !state.vertices ? "Open a mesh to see whether its forms are integrable."
      : failed ? `No report: the service refused this mesh (${failed.title}).`
        : "Computing the integrability report…";
    setStats("integrability-stats", [["Report", failed ? failed.detail : "–", "wrap"]]);
    $("integrability-note").textContent = "";
    return;
  }
  const [ok, text] = integrabilityVerdict(r);
  verdict.className = `verdict ${ok ? "ok" : "bad"}`;
  verdict.textContent = text;
  const topo = r.topology;
  const worst = document.createDocumentFragment();
  r.worst_vertices.slice(0, 3).forEach((v, k) => {
    if (k) worst.append(" ");
    worst.append(num(`v${v}: ${fmt(r[state.defectPart][v], 2)}`));
  });
  const parts = Object.entries(DEFECT_LABELS).map(([key, label]) => [
    `${label} vertex defect (max)`, num(`${fmt(maxOf(r[key]), 3)} rad`),
    key === state.defectPart ? "selected" : ""]);
  setStats("integrability-stats", [
    ["Integrable", badge(r.integrable)],
    ...parts,
    ["Tolerance", num(fmt(r.tolerance))],
    ["Failing vertices", num(String(r.failing_vertices.length))],
    ["Triangle violations", num(String(r.triangle_violations.length))],
    ["Components · genus", num(`${topo.n_components} · ${topo.genus}`)],
    ["Boundary loops", num(String(topo.boundary_loops.length))],
    ["Global loops", loopsText(r), "wrap"],
    ["Worst", r.worst_vertices.length ? worst : "–", "wrap"],
  ]);
  $("integrability-note").textContent = r.integrable
    ? "A surface with exactly these edge lengths and angles exists (this one), so there is "
      + "nothing to colour. To see forms that do not fit, open Rebuild (4) and scale the angles."
    : "No surface has exactly these forms: the colours show where they fail, and a "
      + "reconstruction is the closest compromise.";
}

async function fetchBlob(path) {
  const response = await api.request(path, { method: "GET", accept: "*/*" });
  return response.blob();
}

/** The sample menu names the mesh on screen ("Choose a sample…" for any other mesh), also
 * after a load that failed. */
function showSampleChoice() {
  $("sample-select").value = state.source === "sample" ? state.name : "";
}

async function loadSample(file) {
  try {
    const mesh = await withProgress(`Loading ${file}…`, async () => {
      const blob = await fetchBlob(`/static/samples/${encodeURIComponent(file)}`);
      return inWorker("readMesh", { file: blob, name: file }, `reading ${file}`);
    });
    await openMesh(mesh, file, "sample", { sampleUp: samples.find((s) => s.file === file)?.up });
  } finally {
    showSampleChoice();
  }
}

async function openUpload(file) {
  try {
    const mesh = await withProgress(`Reading ${file.name}…`, () => inWorker("readMesh", { file,
      name: file.name }, `reading ${file.name}`));
    await openMesh(mesh, file.name, "upload");
  } finally {
    showSampleChoice();
  }
}

// ------------------------------------------------------------------ forms -> reconstruct

const FORM_KEYS = ["faces", "edges", "lengths", "angles"];

function reconstructInput(input, refine) {
  // options.refine: null (the default) refines when the linear answer needs it; false asks
  // for the linear least-squares answer. Sent only to servers that know the option.
  return refine === undefined || !caps.refine ? input : { ...input, options: { refine } };
}

/**
 * Rebuild a surface from a forms document and show it. `from` is the mesh the forms came
 * from, when there is one ({vertices, up, upSource}): the answer is moved rigidly onto it
 * and keeps its up axis (the service's answer has an arbitrary placement).
 */
async function reconstructForms(doc, name, source = name, from = null) {
  if (!doc || typeof doc !== "object" || Array.isArray(doc)) {
    throw new api.ApiError({ title: "Not a forms document",
      detail: `${source}: expected a JSON object with ${FORM_KEYS.join(", ")} (the output of POST /v1/forms)` });
  }
  const missing = FORM_KEYS.filter((k) => !(k in doc));
  if (missing.length) {
    throw new api.ApiError({ title: "Not a forms document",
      detail: `${source}: missing ${missing.join(", ")}; upload the output of POST /v1/forms` });
  }
  const input = Object.fromEntries(FORM_KEYS.map((k) => [k, doc[k]]));
  const { integrability, result } = await withProgress("Rebuilding the surface…", async (signal) => {
    const arrays = api.formsArrays(input);  // null: not well-formed, JSON names the element
    const report = arrays ? await api.postArrays("/v1/integrability", {}, arrays, { signal })
      : await api.postJson("/v1/integrability", input, { signal });
    const mesh = await api.runJob("reconstruct", reconstructInput(input), { signal,
      onProgress: jobProgress("Rebuild") });
    return { integrability: report, result: mesh };
  }, { cancellable: true });
  const refinement = result.report?.refinement ?? null;
  const reconstruction = { input, report: result.report, refinement, integrability,
    alignTo: from?.vertices ?? null, refined: null, linear: null,
    showing: refinement?.refined ? "refined" : "linear" };
  const vertices = placedAnswer(reconstruction, result.vertices);
  reconstruction[reconstruction.showing] = vertices;
  // The Mesh panel reports the shown mesh; the Rebuild panel the forms it came from.
  await openMesh({ vertices, faces: result.faces }, name, "reconstruction", { reconstruction,
    up: from?.up, upSource: from?.upSource });
  showTab("forms");
}

/** An answer's vertices (rows) as shown: flat, and on the mesh the forms came from. */
function placedAnswer(rec, rows) {
  const vertices = flatten3(rows);
  return rec.alignTo && rec.alignTo.length === vertices.length
    ? rigidAlign(vertices, rec.alignTo) : vertices;
}

/** Show the refined or the linear reconstruction (fetched the first time it is asked for). */
async function showAnswer(which) {
  const rec = state.reconstruction;
  if (!rec || rec.showing === which) return;
  if (which === "linear" && !rec.linear) {
    const result = await withProgress("Linear answer…", (signal) => api.runJob("reconstruct",
      reconstructInput(rec.input, false), { signal, onProgress: jobProgress("Linear") }),
    { cancellable: true });
    rec.linear = placedAnswer(rec, result.vertices);
  }
  rec.showing = which;
  const vertices = rec[which];
  closeTransport();
  for (const h of state.handles) view.scene.remove(h.pivot);
  view.attachGizmo(null);
  Object.assign(state, { vertices, rest: vertices.slice(), handles: [], active: null,
    selection: [], deformed: false, distortion: null, undo: [], redo: [] });
  state.reference = meshForms(vertices, state.faces, state.topo);
  view.updatePositions(vertices);
  view.buildHelpers();  // the camera stays: the two answers are seen at the same scale
  renderHandles();
  renderDistortion();
  renderReconstruction();
  state.forms = state.integrability = null;
  renderIntegrability();
  enableColorOptions();
  refreshColors();
  updateStatus();
  await analyze();
}

/** The residual table: length and angle errors of the linear and the refined answer. */
function renderResiduals(f) {
  $("residuals").hidden = !f?.refined;
  const body = $("residual-rows");
  body.replaceChildren();
  if (!f?.refined) return;
  const rows = [
    ["Length error, mean", (r) => pct(residual(r, "length_error", "mean"))],
    ["Length error, max", (r) => pct(residual(r, "length_error", "max"))],
    ["Angle error, mean", (r) => deg(residual(r, "angle_error", "mean"))],
    ["Angle error, max", (r) => deg(residual(r, "angle_error", "max"))],
  ];
  for (const [label, cell] of rows) {
    const tr = document.createElement("tr");
    for (const text of [label, cell(f.before), cell(f.after)]) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.append(td);
    }
    body.append(tr);
  }
}

/** A residual summary of report.refinement ("before"/"after"): nested summaries
 * ({length_error: {mean, max}, ...}) or flat keys (length_error_mean, ...). */
function residual(r, kind, stat) {
  return r?.[kind]?.[stat] ?? r?.[`${kind}_${stat}`];
}

function renderReconstruction() {
  const rec = state.reconstruction;
  // Comparing needs the linear answer, i.e. a server that takes options.refine.
  $("compare-row").hidden = !(rec?.refinement?.refined && caps.refine);
  if (!rec) {
    setStats("forms-stats", []);
    renderResiduals(null);
    $("forms-note").textContent = "";
    return;
  }
  const r = rec.report || {};
  const f = rec.refinement;
  const seconds = r.timings ? Object.values(r.timings).reduce((a, b) => a + b, 0) : null;
  const rows = [
    ["Rebuilt", num(`${(state.vertices.length / 3).toLocaleString("en")} vertices`)],
    ["Forms integrable", badge(rec.integrability.integrable)],
    ["Forms' vertex defect (max)", num(`${fmt(maxOf(rec.integrability.vertex_defect))} rad`)],
    ["Forms' global loops", loopsText(rec.integrability), "wrap"],
    ["Method", r.solve_path === "tree-integration" ? "exact integration" : "least squares"],
  ];
  if (f?.refined) {
    if (caps.refine) rows.push(["Showing", rec.showing === "refined" ? "refined answer" : "linear answer"]);
    rows.push(["Refinement", num(`${f.iterations} steps, ${(1000 * f.seconds).toFixed(0)} ms`
      + (f.converged ? "" : " (not converged)"))]);
  } else if (seconds !== null) {
    rows.push(["Solve time", num(`${(1000 * (seconds + (f?.seconds ?? 0))).toFixed(0)} ms`)]);
  }
  setStats("forms-stats", rows);
  renderResiduals(f);
  document.querySelector(`input[name="answer"][value="${rec.showing}"]`).checked = true;
  $("forms-note").textContent = f?.refined
    ? "The linear answer can shrink or crumple a surface whose forms do not fit; the refined "
      + "one shown here is the nearest surface to the forms."
      + (caps.refine ? " Switch to Linear to compare." : "")
    : rec.integrability.integrable ? "The forms fit together: this is the surface they describe."
      : "The forms do not fit together: this is the least-squares compromise.";
}

async function openFormsFile(file) {
  let doc;
  try {
    doc = JSON.parse(await file.text());
  } catch (err) {
    throw new api.ApiError({ title: "Invalid JSON", detail: `${file.name}: ${err.message}` });
  }
  await reconstructForms(doc, `${file.name} (reconstructed)`, file.name);
}

/** A forms document with plain arrays (faces, edges as rows) from typed or nested forms,
 * the dihedral angles scaled by `scale` (and kept in [-pi, pi]). */
function formsInput(f, scale = 1) {
  const rows = (a, w) => (Array.isArray(a) ? a
    : Array.from({ length: a.length / w }, (_, i) => Array.from(a.subarray(w * i, w * i + w))));
  return { faces: rows(f.faces, 3), edges: rows(f.edges, 2), lengths: Array.from(f.lengths),
    angles: Array.from(f.angles, (a) => Math.max(-Math.PI, Math.min(Math.PI, a * scale))) };
}

async function bendForms() {
  const scale = Number($("angle-scale").value);
  if (!Number.isFinite(scale)) throw new api.ApiError({ title: "Invalid angle scale",
    detail: "enter a number, e.g. 0.8" });
  if (!state.forms) return;
  const stem = state.name.replace(/ \(.*\)$/, "");
  await reconstructForms(formsInput(state.forms, scale), `${stem} (angles × ${scale})`, undefined,
    { vertices: state.vertices, up: state.up, upSource: state.upSource });
}

// ---------------------------------------------------------------------------- flatten

function hideFlat() {
  $("view-flat").hidden = true;
  $("viewport").classList.remove("split");
  if (state.colorMode === "checker") setColorMode("plain");
}

async function flatten() {
  if (!state.vertices) return;
  const input = { vertices: rows3(state.vertices), faces: rows3(state.faces),
    options: { orthonormalize: $("flatten-orthonormalize").checked } };
  const result = await withProgress("Flattening…", (signal) => api.runJob("parameterize", input,
    { signal, onProgress: jobProgress("Flatten") }), { cancellable: true });
  const uv = new Float64Array(result.uv.length * 2);
  result.uv.forEach(([u, v], i) => {
    uv[2 * i] = u;
    uv[2 * i + 1] = v;
  });
  $("view-flat").hidden = false;
  $("viewport").classList.add("split");
  await new Promise((resolve) => requestAnimationFrame(resolve));
  const texcoords = flatView.show(uv, state.faces, state.topo.edges, result.flipped_faces);
  state.flat = { uv, flipped: result.flipped_faces, report: result.report, texcoords };
  view.resize();
  view.frame({ keep: true });
  const r = result.report;
  const flips = result.flipped_faces.length;
  $("flip-note").textContent = flips ? `${flips} flipped face(s) in red` : "no flipped faces";
  $("flip-note").className = `flip-note${flips ? " bad" : ""}`;
  setStats("flatten-stats", [
    ["Flipped faces", badge(flips === 0, "0", String(flips))],
    ["Length change (mean)", pct(r.length_change_summary.mean)],
    ["Length change (max)", pct(r.length_change_summary.max)],
    ["Angle distortion (max)", deg(r.angle_distortion_summary.max)],
    ["Area ratio − 1 (rms)", fmt(r.area_ratio_summary.rms)],
  ]);
  enableColorOptions();
  setColorMode("checker");
}

// ---------------------------------------------------------------------------- handles

function renderHandles() {
  const list = $("handle-list");
  list.replaceChildren();
  state.handles.forEach((h) => {
    const li = document.createElement("li");
    li.className = h === state.active ? "active" : "";
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = `#${h.color.toString(16).padStart(6, "0")}`;
    const name = document.createElement("span");
    name.className = "name";
    name.textContent = `Handle ${h.id} · ${h.vertices.length} ${h.vertices.length > 1 ? "vertices" : "vertex"}`
      + (h === state.active ? " · active" : "");
    const remove = document.createElement("button");
    remove.type = "button";
    remove.textContent = "Remove";
    remove.addEventListener("click", (event) => {
      event.stopPropagation();
      action(removeHandle)(h);
    });
    li.append(swatch, name, remove);
    li.addEventListener("click", () => setActive(h));
    list.append(li);
  });
  const count = state.selection.length;
  $("selection-count").textContent = `${count} selected`;
  $("make-handle").disabled = !count;
  $("reset-shape").disabled = !state.handles.length;
  $("remove-handles").disabled = !state.handles.length;
  $("undo").disabled = !state.undo.length;
  $("redo").disabled = !state.redo.length;
  if (!state.handles.length) {
    $("transport").textContent = state.vertices ? "No handles yet." : "";
  } else if (state.handles.length === 1) {
    $("transport").textContent = "One handle moves the mesh rigidly: add a second one to anchor it.";
  } else if (state.transport) {
    $("transport").textContent = transportText();
  }
  refreshMarkers();
}

function refreshMarkers() {
  if (!state.vertices) return;
  view.setMarkers(state.vertices, state.selection, state.handles);
}

function setActive(handle) {
  state.active = handle;
  view.attachGizmo(handle && state.tab === "deform" ? handle.pivot : null);
  renderHandles();
}

function select(ids, { toggle = false } = {}) {
  const used = new Set(state.handles.flatMap((h) => h.vertices));
  const current = new Set(state.selection);
  for (const v of ids) {
    if (used.has(v)) continue;
    if (toggle && current.has(v)) current.delete(v);
    else current.add(v);
  }
  state.selection = [...current];
  renderHandles();
}

/** Targets of all handle vertices, and the rotation of each rotation group. */
function handleTargets() {
  const count = state.handles.reduce((s, h) => s + h.vertices.length, 0);
  const positions = new Float64Array(3 * count);
  const rotations = [];
  const offset = new THREE.Vector3(), m = new THREE.Matrix4();
  let k = 0;
  for (const h of state.handles) {
    for (let i = 0; i < h.vertices.length; i++) {
      offset.set(h.start[3 * i], h.start[3 * i + 1], h.start[3 * i + 2]).sub(h.center)
        .applyQuaternion(h.pivot.quaternion).add(h.pivot.position);
      positions.set([offset.x, offset.y, offset.z], 3 * k++);
    }
    if (h.rotationFaces.length) {
      const e = m.makeRotationFromQuaternion(h.pivot.quaternion).elements;
      rotations.push([[e[0], e[4], e[8]], [e[1], e[5], e[9]], [e[2], e[6], e[10]]]);
    }
  }
  return { positions, rotations };
}

function setupFor() {
  const taken = new Set();
  for (const h of state.handles) h.rotationFaces = facesAround(h.vertices, state.faces, taken);
  const { positions, rotations } = handleTargets();
  return {
    rest: state.rest, faces: state.faces,
    handles: state.handles.flatMap((h) => h.vertices),
    rotationGroups: state.handles.filter((h) => h.rotationFaces.length).map((h) => h.rotationFaces),
    orthonormalize: state.orthonormalize,
    // refine: sent only to servers that know it (a session's default is linear drags)
    refine: caps.deformRefine ? state.refineDrags : undefined,
    initialPositions: positions, initialRotations: rotations,
  };
}

/** The current shape becomes the rest shape of the next session (handles keep their place). */
function bake() {
  state.rest = state.vertices.slice();
  const { positions } = handleTargets();
  let k = 0;
  for (const h of state.handles) {
    h.start = positions.slice(3 * k, 3 * (k + h.vertices.length));
    k += h.vertices.length;
    h.center.copy(h.pivot.position);
    h.pivot.quaternion.identity();
  }
  state.deformed = false;
}

function closeTransport(options) {
  if (state.transport) state.transport.close(options);
  state.transport = null;
}

/** Session statuses that mean "no session for you now": deform per update instead. */
const SESSION_UNAVAILABLE = [404, 405, 429, 501, 503];

let transportGeneration = 0;

async function rebuildTransport({ solve = true } = {}) {
  const generation = ++transportGeneration;
  closeTransport();
  if (!state.handles.length) {
    updateStatus();
    return;
  }
  const setup = setupFor();
  // ?transport=http (session, no WebSocket) or ?transport=deform (no session) pin a path.
  let transport = caps.sessions && TRANSPORT !== "deform"
    ? new SessionTransport(setup, { websocket: TRANSPORT !== "http",
      onRefined: (vertices) => { if (transport === state.transport) applyShape(vertices); } })
    : new DeformTransport(setup);
  let note = "";
  await withProgress("Preparing the deformation (factorization)…", async () => {
    try {
      await transport.open();
    } catch (err) {
      if (!(transport instanceof SessionTransport && err instanceof api.ApiError
        && SESSION_UNAVAILABLE.includes(err.status))) throw err;
      const info = api.describe(err);
      note = ` (no session: ${info.title}: ${info.detail})`;
      console.warn("[ffs] sessions unavailable, deforming per request", info);
      transport = new DeformTransport(setup);
      transport.label = "HTTP: POST /v1/deform per update";
    }
  });
  if (generation !== transportGeneration) {  // superseded while it opened
    transport.close();
    return;
  }
  transport.note = note;
  state.transport = transport;
  state.transportKey = transportKey();
  if (state.handles.length > 1) $("transport").textContent = transportText();
  updateStatus();
  if (solve) requestSolve();
}

/** What the live updates run on, in words (the technical label stays in state.transport). */
function transportText() {
  const t = state.transport;
  const how = t.kind === "session" ? "set up once for these handles"
    : "each drag solved from scratch (slower)";
  const last = state.lastSolveMs !== null ? `, ${state.lastSolveMs.toFixed(0)} ms per update` : "";
  return `Live: ${how}${last}.`;
}

/** What a transport was opened for: the rest shape, the handle set and the options. */
function transportKey() {
  return { rest: state.rest, handles: state.handles.map((h) => h.id).join(","),
    orthonormalize: state.orthonormalize, refine: state.refineDrags };
}

function transportCurrent() {
  const key = state.transportKey, now = transportKey();
  return !!state.transport && !!key && key.rest === now.rest && key.handles === now.handles
    && key.orthonormalize === now.orthonormalize && key.refine === now.refine;
}

function requestSolve() {
  state.solveWanted = true;
  if (!state.solving) state.solving = track(solveLoop());
}

async function solveLoop() {
  try {
    while (state.solveWanted && state.transport) {
      state.solveWanted = false;
      const transport = state.transport;
      const { positions, rotations } = handleTargets();
      const t0 = performance.now();
      let vertices;
      try {
        vertices = await transport.solve(positions, rotations);
        if (transport.settled) track(transport.settled());  // the refined shape to come
      } catch (err) {
        if (transport !== state.transport) continue; // replaced meanwhile: stale
        if (transport.kind === "session" && (err.status === 410 || err.status === 404)
          && !transport.replaced) {
          // The session expired (FFS_SESSION_TTL) or its worker went away: open a new one
          // for the same handles and carry on.
          console.warn("[ffs] session gone, opening a new one", api.describe(err));
          transport.replaced = true;
          transport.id = null;  // nothing left to delete
          await rebuildTransport();
          state.solveWanted = true;
          continue;
        }
        throw err;
      }
      if (transport !== state.transport) continue;
      state.lastSolveMs = performance.now() - t0;
      state.solves++;
      applyShape(vertices);
      if (!state.solveWanted) refitIfOutgrown();
    }
  } catch (err) {
    showError(err);
  } finally {
    state.solving = null;
  }
}

function applyShape(vertices, { deformed = true } = {}) {
  const t0 = performance.now();
  state.vertices = vertices;
  state.deformed = deformed;
  view.updatePositions(vertices);
  state.distortion = distortion(state.reference, meshForms(vertices, state.faces, state.topo),
    state.topo);
  renderDistortion();
  enableColorOptions();
  if (state.colorMode !== "distortion" && state.colorMode !== "checker") state.colorMode = "distortion";
  refreshColors();
  refreshMarkers();
  if (state.handles.length > 1 && state.transport) $("transport").textContent = transportText();
  updateStatus();
  state.lastApplyMs = performance.now() - t0;
}

async function makeHandle(ids = state.selection) {
  const used = new Set(state.handles.flatMap((h) => h.vertices));
  const vertices = [...new Set(ids)].filter((v) => !used.has(v));
  if (!vertices.length) throw new api.ApiError({ title: "Nothing to make a handle of",
    detail: "select vertices that are not already in a handle" });
  remember();
  if (state.deformed) bake();
  const start = new Float64Array(3 * vertices.length);
  const center = new THREE.Vector3();
  vertices.forEach((v, k) => {
    start.set(state.vertices.subarray(3 * v, 3 * v + 3), 3 * k);
    center.x += state.vertices[3 * v] / vertices.length;
    center.y += state.vertices[3 * v + 1] / vertices.length;
    center.z += state.vertices[3 * v + 2] / vertices.length;
  });
  const pivot = new THREE.Object3D();
  pivot.position.copy(center);
  const handle = { id: ++handleCounter, vertices, start, center: center.clone(), pivot,
    color: HANDLE_COLORS[(handleCounter - 1) % HANDLE_COLORS.length], rotationFaces: [] };
  view.scene.add(pivot);
  state.handles.push(handle);
  state.selection = state.selection.filter((v) => !vertices.includes(v));
  setActive(handle);
  await rebuildTransport();
}

async function removeHandle(handle) {
  remember();
  if (state.deformed) bake();
  state.handles = state.handles.filter((h) => h !== handle);
  view.scene.remove(handle.pivot);
  setActive(state.handles.at(-1) ?? null);
  await rebuildTransport();
}

async function removeHandles() {
  remember();
  closeTransport();
  for (const h of state.handles) view.scene.remove(h.pivot);
  state.handles = [];
  state.rest = state.vertices.slice();
  state.deformed = false;
  setActive(null);
  updateStatus();
}

async function resetShape() {
  remember();
  for (const h of state.handles) {
    h.pivot.position.copy(h.center);
    h.pivot.quaternion.identity();
  }
  view.request();
  if (state.transport) requestSolve();
}

function onHandleMoved() {
  if (state.transport) requestSolve();
}

// ------------------------------------------------------------------------- undo / redo
// A step is a drag, a reset, or adding/removing handles. Each keeps what it started from:
// the rest shape, the shown vertices and every handle's vertices and pose. Undo puts that
// back (no solve: the vertices are the ones shown then) and reopens the session only when
// the rest shape or the handle set differ from the open one.

function snapshot() {
  return {
    rest: state.rest, vertices: state.vertices, deformed: state.deformed, active: state.active,
    distortion: state.distortion,
    handles: state.handles.map((h) => ({ handle: h, vertices: h.vertices, start: h.start,
      center: h.center.clone(), position: h.pivot.position.clone(),
      quaternion: h.pivot.quaternion.clone() })),
  };
}

/** Whether the whole shape is on screen, below the view's toolbar (`toolbar`) or anywhere
 * on the canvas. */
function shapeInView({ toolbar = true } = {}) {
  const canvas = view.canvas.getBoundingClientRect();
  const bar = $("view-toolbar").getBoundingClientRect();
  return view.fits(state.vertices, { top: toolbar ? Math.max(0, bar.bottom - canvas.top) : 0 });
}

/** After a step (once the gizmo is let go): a shape that was on screen and grew out of it,
 * or under the toolbar, is fitted again from the same direction. */
function refitIfOutgrown() {
  if (!state.vertices || view.gizmo.dragging || !state.inViewBefore) return;
  if (!shapeInView()) {
    view.frame({ keep: true });
    state.inViewBefore = shapeInView({ toolbar: false });
  }
}

function remember() {
  if (!state.vertices) return;
  state.inViewBefore = shapeInView({ toolbar: false });
  state.undo.push(snapshot());
  if (state.undo.length > HISTORY_LIMIT) state.undo.shift();
  state.redo = [];
  $("undo").disabled = false;
  $("redo").disabled = true;
}

async function restore(snap) {
  for (const h of state.handles) view.scene.remove(h.pivot);
  state.handles = snap.handles.map((s) => {
    const h = s.handle;
    Object.assign(h, { vertices: s.vertices, start: s.start });
    h.center.copy(s.center);
    h.pivot.position.copy(s.position);
    h.pivot.quaternion.copy(s.quaternion);
    view.scene.add(h.pivot);
    return h;
  });
  state.rest = snap.rest;
  state.vertices = snap.vertices;
  state.deformed = snap.deformed;
  state.distortion = snap.distortion;
  view.updatePositions(state.vertices);
  renderDistortion();
  enableColorOptions();
  if (state.colorMode === "distortion" && !state.distortion) state.colorMode = "plain";
  refreshColors();
  setActive(state.handles.includes(snap.active) ? snap.active : state.handles.at(-1) ?? null);
  if (!transportCurrent()) {
    if (state.handles.length) await rebuildTransport({ solve: false });
    else {
      closeTransport();
      state.transportKey = null;
    }
  }
  updateStatus();
}

// Undo and redo: take the newest snapshot of one stack, keep the current state on the other.
async function travel(from, to) {
  if (state.solving) await state.solving;
  const snap = from.pop();
  if (!snap) return;
  to.push(snapshot());
  await restore(snap);
}

function undo() { return travel(state.undo, state.redo); }
function redo() { return travel(state.redo, state.undo); }

function renderDistortion() {
  const canvas = $("histogram");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const d = state.distortion;
  if (!d) {
    ctx.fillStyle = "#9aa5b1";
    ctx.font = "22px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.fillText("Drag a handle to see the distortion", canvas.width / 2, canvas.height / 2);
    setStats("distortion-stats", []);
    return;
  }
  const length = state.distortionKind === "length";
  const values = length ? d.length : d.angle;
  const { counts, top } = histogram(values, 20);
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
  ctx.fillText(length ? pct(top) : deg(top), W - pad.r, H - 8);
  ctx.textAlign = "center";
  ctx.fillText(`edges per bin (√ scale, max ${maxCount})`, W / 2, H - 8);
  const s = length ? d.lengthSummary : d.angleSummary;
  const f = length ? pct : deg;
  setStats("distortion-stats", [["Mean", f(s.mean)], ["RMS", f(s.rms)], ["95th percentile", f(s.p95)],
    ["Max", f(s.max)]]);
}

// ---------------------------------------------------------------------------- download

async function downloadGlb() {
  const blob = await withProgress("Encoding GLB…", () => api.meshGlb(state.vertices,
    state.faces));
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = `${state.name.replace(/\.[^.]*$|\s*\(.*\)$/g, "").replace(/[^\w.-]+/g, "-") || "mesh"}.glb`;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
  return blob.size;
}

// ------------------------------------------------------------------------ interaction

function installPointer() {
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
      select(ids);
      if (ids.length) showTab("deform");
      return;
    }
    const moved = Math.hypot(event.clientX - start.x, event.clientY - start.y);
    if (moved < 5 && !start.gizmo && event.target === canvas) {
      const v = view.pickVertex(event.clientX, event.clientY);
      if (v >= 0) {
        select([v], { toggle: true });
        showTab("deform");
      }
    }
  });
  view.gizmo.addEventListener("mouseDown", () => remember());
  view.gizmo.addEventListener("dragging-changed", (event) => event.value || refitIfOutgrown());
  view.gizmo.addEventListener("objectChange", onHandleMoved);
  window.addEventListener("keydown", onKey);
}

function toggleCheckbox(id) {
  $(id).checked = !$(id).checked;
  $(id).dispatchEvent(new Event("change"));
}

function setHelp(open) {
  $("help").hidden = !open;
  if (open) $("help-close").focus();
}

/** Keyboard shortcuts (listed in the help overlay, index.html). */
function onKey(event) {
  // Typing in a field is not a shortcut (a focused checkbox or button does not count).
  const field = event.target.closest?.("select, textarea, input");
  if (field && !(field.tagName === "INPUT" && ["checkbox", "radio", "file", "button"].includes(field.type))) return;
  const key = event.key, ctrl = event.ctrlKey || event.metaKey;
  if (key === "?") {
    setHelp($("help").hidden);
  } else if (key === "Escape") {
    if (!$("help").hidden) setHelp(false);
    else {
      state.selection = [];
      renderHandles();
    }
  } else if (ctrl && (key === "z" || key === "Z")) {
    event.preventDefault();
    action(event.shiftKey ? redo : undo)();
  } else if (ctrl && key === "y") {
    event.preventDefault();
    action(redo)();
  } else if (ctrl || event.altKey) {
    return;
  } else if (key >= "1" && key <= "4") {
    showTab(TABS[Number(key) - 1]);
  } else if (key === "w" || key === "e") {
    const mode = key === "w" ? "translate" : "rotate";
    document.querySelector(`input[name="gizmo-mode"][value="${mode}"]`).checked = true;
    view.gizmo.setMode(mode);
  } else if ((key === "Delete" || key === "Backspace") && state.active) {
    action(removeHandle)(state.active);
  } else if (key === "h" && state.selection.length) {
    action(makeHandle)();
  } else if (key === "f" && state.vertices) {
    view.frame({ keep: true });
  } else if (key === "r" && state.vertices) {
    view.frame();
  } else if (key === "g") {
    toggleCheckbox("grid-toggle");
  } else if (key === "m") {
    toggleCheckbox("wireframe");
  } else if (key === "u" && state.vertices) {
    setUp(UP_AXES[(UP_AXES.indexOf(state.up) + 1) % UP_AXES.length]);
  }
}

function installPanels() {
  $("sample-select").addEventListener("change", (event) => {
    if (event.target.value) action(loadSample)(event.target.value);
  });
  $("mesh-file").addEventListener("change", (event) => {
    const file = event.target.files[0];
    event.target.value = "";
    if (file) action(openUpload)(file);
  });
  $("forms-file").addEventListener("change", (event) => {
    const file = event.target.files[0];
    event.target.value = "";
    if (file) action(openFormsFile)(file);
  });
  $("wireframe").addEventListener("change", (event) => view.setWireframe(event.target.checked));
  $("grid-toggle").addEventListener("change", (event) => view.setHelpers(event.target.checked));
  $("up-axis").addEventListener("change", (event) => {
    if (state.vertices) setUp(event.target.value);
  });
  $("fit-view").addEventListener("click", () => state.vertices && view.frame({ keep: true }));
  $("reset-view").addEventListener("click", () => state.vertices && view.frame());
  for (const tab of TABS) $(`tab-${tab}`).addEventListener("click", () => showTab(tab));
  $("help-open").addEventListener("click", () => setHelp(true));
  $("help-close").addEventListener("click", () => setHelp(false));
  $("help").addEventListener("click", (event) => {
    if (event.target === $("help")) setHelp(false);
  });
  $("undo").addEventListener("click", action(undo));
  $("redo").addEventListener("click", action(redo));
  $("show-defect").addEventListener("click", () => setColorMode("defect"));
  for (const input of document.querySelectorAll('input[name="answer"]')) {
    input.addEventListener("change", action(() => showAnswer(input.value)));
  }
  $("download-glb").addEventListener("click", action(downloadGlb));
  $("flatten").addEventListener("click", action(flatten));
  $("close-flat").addEventListener("click", () => {
    hideFlat();
    view.resize();
    view.frame({ keep: true });
  });
  $("bend-forms").addEventListener("click", action(bendForms));
  $("make-handle").addEventListener("click", action(() => makeHandle()));
  $("clear-selection").addEventListener("click", () => {
    state.selection = [];
    renderHandles();
  });
  $("reset-shape").addEventListener("click", action(resetShape));
  $("remove-handles").addEventListener("click", action(removeHandles));
  $("orthonormalize").addEventListener("change", action(async (event) => {
    state.orthonormalize = event.target.checked;
    if (state.handles.length) await rebuildTransport();
  }));
  $("deform-refine").addEventListener("change", action(async (event) => {
    state.refineDrags = event.target.checked;
    if (state.handles.length) await rebuildTransport();
  }));
  $("color-mode").addEventListener("change", (event) => setColorMode(event.target.value));
  for (const input of document.querySelectorAll('input[name="defect-part"]')) {
    input.addEventListener("change", () => {
      state.defectPart = input.value;
      renderIntegrability();
      if (state.integrability) setColorMode("defect");
    });
  }
  for (const input of document.querySelectorAll('input[name="distortion-kind"]')) {
    input.addEventListener("change", () => {
      state.distortionKind = input.value;
      renderDistortion();
      if (state.distortion) setColorMode("distortion");
    });
  }
  for (const input of document.querySelectorAll('input[name="gizmo-mode"]')) {
    input.addEventListener("change", () => view.gizmo.setMode(input.value));
  }
  $("progress-cancel").addEventListener("click", () => progress.controller?.abort());
}

async function loadSampleList() {
  samples = await api.getJson("/static/samples/index.json");
  for (const s of samples) {
    const option = document.createElement("option");
    option.value = s.file;
    option.textContent = s.title;
    option.title = s.note;
    $("sample-select").append(option);
  }
  return samples;
}

// ------------------------------------------------------------------------------ start

async function start() {
  view = new MeshView($("view-3d"));
  flatView = new FlatView($("view-flat"));
  installPointer();
  installPanels();
  renderDistortion();
  const [, capabilities] = await Promise.all([loadSampleList(), api.capabilities()]);
  caps = capabilities;
  $("deform-refine-label").hidden = !caps.deformRefine;
  $("deform-refine").checked = state.refineDrags;
  const wanted = new URLSearchParams(location.search).get("sample");
  const first = wanted ?? samples[0]?.file;
  if (first) await loadSample(first);
  else status("Ready: pick a sample or upload a mesh.");
}

let startup = "starting";
const ready = track(start()).then(() => { startup = "ready"; },
  (err) => { startup = "failed"; showError(err); });
window.addEventListener("pagehide", () => closeTransport({ unloading: true }));

window.app = {
  state, ready, idle,
  toastMs: 8000,
  workerLimits: worker.limits,
  /** What the page is doing, for a test that waited too long. */
  diagnostics: () => ({ startup, busy, mesh: state.name, workerCalls: worker.pending(),
    progress: $("progress").hidden ? null : $("progress-label").textContent,
    errors: state.errors.map((e) => `${e.title}: ${e.detail}`) }),
  get view() { return view; },
  get capabilities() { return caps; },
  loadSample: (file) => action(loadSample)(file),
  select: (ids) => select(ids),
  makeHandle: (ids) => action(makeHandle)(ids),
  setActive: (index) => setActive(state.handles[index]),
  /** Move (and optionally rotate, axis-angle in radians) the active handle, as the gizmo does. */
  dragHandle(dx, dy, dz, { axis, angle } = {}) {
    const h = state.active;
    if (!h) throw new Error("no active handle");
    remember();
    h.pivot.position.add(new THREE.Vector3(dx, dy, dz));
    if (axis) {
      h.pivot.quaternion.premultiply(new THREE.Quaternion()
        .setFromAxisAngle(new THREE.Vector3(...axis).normalize(), angle));
    }
    view.request();
    onHandleMoved();
    return idle();
  },
  /** The POST /v1/deform body equivalent to the current handles. */
  deformRequest() {
    const setup = setupFor();
    const { positions, rotations } = handleTargets();
    return deformBody(setup, positions, rotations);
  },
  handleTargets: () => {
    const { positions, rotations } = handleTargets();
    return { positions: Array.from(positions), rotations };
  },
  vertices: () => Array.from(state.vertices),
  colors: () => Array.from(view.mesh.geometry.getAttribute("color").array),
  screenOf(vertex) {
    const v = state.vertices;
    return view.project(v[3 * vertex], v[3 * vertex + 1], v[3 * vertex + 2]);
  },
  pivotScreen() {
    const p = state.active.pivot.position;
    return view.project(p.x, p.y, p.z);
  },
  /** Vertices whose normal faces the camera and whose screen position is inside the canvas. */
  visibleVertices() {
    const r = view.canvas.getBoundingClientRect();
    return view.verticesInRect(r.left, r.top, r.right, r.bottom, { facing: state.closed });
  },
  setRefine: (on) => {
    $("deform-refine").checked = on;
    $("deform-refine").dispatchEvent(new Event("change"));
    return idle();
  },
  setOrthonormalize: (on) => {
    $("orthonormalize").checked = on;
    $("orthonormalize").dispatchEvent(new Event("change"));
    return idle();
  },
  flatten: () => action(flatten)(),
  downloadGlb: () => action(downloadGlb)(),
  undo: () => action(undo)(),
  redo: () => action(redo)(),
  setUp: (up) => setUp(up),
  showTab,
  setColorMode,
  /** Up vector on screen: the screen direction (y down) of the up axis at the mesh centre. */
  screenUp() {
    const c = view.mesh.geometry.boundingSphere.center, u = view.up, r = view.radius * 0.2;
    const a = view.project(c.x, c.y, c.z), b = view.project(c.x + r * u.x, c.y + r * u.y, c.z + r * u.z);
    return { x: b.x - a.x, y: b.y - a.y };
  },
};
