// The Mesh panel and the view's toolbar: the sample list, opening a sample or a file (read
// in the worker), the mesh's statistics, its up axis (the sample's, a guess, or the user's),
// the GLB download, and the status line's summary of what is on screen.

import * as api from "./api.js";
import { fmt, num, setStats } from "./format.js";
import { bounds, prepareMesh } from "./mesh.js";
import { action, onFileChosen, withProgress } from "./progress.js";
import { state, store } from "./store.js";
import { status } from "./toasts.js";
import { axisVector } from "./viewer.js";

const $ = (id) => document.getElementById(id);
const nextTask = () => new Promise((resolve) => setTimeout(resolve, 0));

/** The up axis of a mesh: the sample's known orientation, else a guess from the bounding
 * box (Z when the mesh is clearly taller in Z than in Y, as scans and CAD files are; Y,
 * the OBJ/glTF convention, otherwise). */
function guessUp(vertices, sampleUp) {
  if (sampleUp) return { up: sampleUp, source: "sample" };
  const { min, max } = bounds(vertices);
  return { up: max[2] - min[2] > 1.15 * (max[1] - min[1]) ? "+z" : "+y", source: "guess" };
}

function drawStatus(s) {
  if (!s.topo) return;
  const parts = [`${s.name}`, `${s.vertices.length / 3} vertices`, `${s.faces.length / 3} faces`];
  if (s.handles.length) parts.push(`${s.handles.length} handle${s.handles.length > 1 ? "s" : ""}`);
  if (s.lastSolveMs !== null) parts.push(`last update ${s.lastSolveMs.toFixed(0)} ms`);
  parts.push(`up: ${s.up.replace("+", "")}${{ guess: " (guessed)", sample: " (sample)" }[s.upSource] ?? ""}`);
  status(parts.join(" · "));
}

const MB = 1024 * 1024;
const bytesText = (b) => (b >= MB ? `${(b / MB).toFixed(b >= 10 * MB ? 0 : 1)} MB`
  : `${Math.ceil(b / 1024)} KB`);

/** The page's tabs that run an operation which only factorizes (GET /v1/me's name, the
 * verb): their limit is their own, under reconstruct's (which goes iterative beyond it). */
const FACTORIZING_TABS = [["deform", "deform"], ["parameterize", "flatten"], ["blend", "blend"]];

/** "a, b or c" */
const anyOf = (words) => (words.length > 1
  ? `${words.slice(0, -1).join(", ")} or ${words.at(-1)}` : words[0]);

/** The factorizing tabs' limits under `below` faces, one entry per limit: [{ faces, verbs }]. */
function tabLimits(byOperation, below) {
  const groups = new Map();
  for (const [name, verb] of FACTORIZING_TABS) {
    const n = byOperation?.[name];
    if (n === undefined || n >= below) continue;
    groups.set(n, [...(groups.get(n) ?? []), verb]);
  }
  return [...groups].sort((a, b) => b[0] - a[0]).map(([faces, verbs]) => ({ faces, verbs }));
}

/** The service's limits under the panel: "up to N faces (M to rebuild, L for a linear
 * answer, D to deform, flatten or blend)", and what they mean for the mesh on screen (m
 * faces): flagged when it is over a limit of the page's operations (over the refined
 * answer's but within the linear answer's: said so; over the faces Deform, Flatten and
 * Blend take: said so), noted when reconstruct solves it iteratively (over the faces its
 * factorization fits: slower). */
function drawLimits(s) {
  const line = $("service-limits"), limits = s.sizeLimits;
  line.hidden = !limits;
  if (!limits) return;
  const m = s.faces ? s.faces.length / 3 : 0;
  const faces = (n) => n.toLocaleString("en");
  const byOperation = limits.max_faces_by_operation;
  const solve = byOperation?.reconstruct ?? limits.max_faces;
  const linear = limits.max_linear_faces_by_operation?.reconstruct ?? solve;
  const direct = limits.max_direct_faces_by_operation?.reconstruct ?? solve;
  const tabs = tabLimits(byOperation, Math.min(solve, limits.max_faces));
  const within = [solve < limits.max_faces ? `${faces(solve)} to rebuild` : null,
    linear > solve ? `${faces(linear)} for a linear answer` : null,
    ...tabs.map((t) => `${faces(t.faces)} to ${anyOf(t.verbs)}`)].filter(Boolean);
  const text = `Service: up to ${faces(limits.max_faces)} faces`
    + (within.length ? ` (${within.join(", ")})` : "")
    + `, files up to ${bytesText(limits.max_body_bytes)}.`;
  const over = m > solve;
  let note = "";
  if (m > linear) note = " This mesh is over the limit to rebuild.";
  else if (over) note = ` This mesh is over the limit to rebuild refined; its linear answer `
    + `(up to ${faces(linear)} faces) fits.`;
  else if (m > direct) note = ` This mesh is over the ${faces(direct)} faces a factorization `
    + "fits: it is rebuilt iteratively (slower).";
  const tooLarge = tabs.filter((t) => m > t.faces).flatMap((t) => t.verbs);
  if (tooLarge.length) note += ` It is too large to ${anyOf(tooLarge)}.`;
  line.textContent = text + note;
  line.classList.toggle("over-limit", over || tooLarge.length > 0);
  line.classList.toggle("iterative", !over && m > direct);
}

/** A file over the service's body limit is refused here, before it is sent. */
function checkFileSize(file, limits) {
  if (!limits || file.size <= limits.max_body_bytes) return;
  throw new api.ApiError({ status: 413, title: "File too large", kind: "body-too-large",
    detail: `${file.name} is ${bytesText(file.size)}; this service takes files up to `
      + `${bytesText(limits.max_body_bytes)} (FFS_MAX_BODY_BYTES).` }, "upload");
}

function drawMesh(s) {
  if (!s.topo) return;
  const n = s.vertices.length / 3, m = s.faces.length / 3;
  const E = s.topo.edges.length / 2;
  const { min, max } = bounds(s.vertices);
  const boundary = s.boundaryEdges;
  $("empty-state").hidden = true;
  $("mesh-title").textContent = `${s.name}${s.source === "sample" ? " (sample)" : ""}`;
  $("download-glb").disabled = false;
  setStats("mesh-stats", [
    ["Vertices · faces", num(`${n.toLocaleString("en")} · ${m.toLocaleString("en")}`)],
    ["Edges", num(`${E.toLocaleString("en")}${boundary ? ` (${boundary.toLocaleString("en")} on the boundary)`
      : " (closed)"}`)],
    ["Size", num(max.map((x, k) => fmt(x - min[k])).join(" × "))],
    ["Mean edge", num(fmt(s.meanEdge))],
  ]);
}

/** The sample menu names the mesh on screen ("Choose a sample…" for any other mesh), also
 * after a load that failed. */
function showSampleChoice() {
  $("sample-select").value = state.source === "sample" ? state.name : "";
}

function downloadName(name) {
  return `${name.replace(/\.[^.]*$|\s*\(.*\)$/g, "").replace(/[^\w.-]+/g, "-") || "mesh"}.glb`;
}

/** The Mesh panel. `analyze()` computes the report of the shape on screen (analysis
 * panel); `inWorker(kind, args, label)` runs a worker call. */
export function installMeshPanel({ view, inWorker, analyze }) {
  let samples = [];

  /** Show a mesh (prepared by mesh.prepareMesh, or {vertices, faces} as nested arrays) and
   * analyse it. `extra`: {up, upSource} (kept from the mesh it came from), sampleUp,
   * reconstruction (the Rebuild panel's answer). */
  async function openMesh(mesh, name, source, extra = {}) {
    const p = mesh.topo ? mesh : prepareMesh(mesh.vertices, mesh.faces);
    store.set({ handles: [], active: null, selection: [] });  // closes the deformation
    const { up, source: upSource } = extra.up ? { up: extra.up, source: extra.upSource ?? "user" }
      : guessUp(p.vertices, extra.sampleUp);
    view.setUp(axisVector(up), { refit: false });
    view.setMesh(p.vertices, p.faces, p.topo.edges);
    await nextTask();  // a big mesh: let the page breathe between building and panels
    store.set({
      name, source, vertices: p.vertices, faces: p.faces, topo: p.topo, reference: p.reference,
      meanEdge: p.meanEdge, boundaryEdges: p.boundaryEdges, closed: p.boundaryEdges === 0,
      up, upSource, rest: p.vertices.slice(), deformed: false, distortion: null, flat: null,
      integrability: null, forms: null, analysisError: null, colorMode: "plain",
      lastSolveMs: null, solves: 0, undo: [], redo: [], reconstruction: extra.reconstruction ?? null,
    });
    showSampleChoice();
    await analyze();
  }

  async function fetchBlob(path) {
    const response = await api.request(path, { method: "GET", accept: "*/*" });
    return response.blob();
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
    checkFileSize(file, state.sizeLimits);
    try {
      const mesh = await withProgress(`Reading ${file.name}…`, () => inWorker("readMesh", { file,
        name: file.name }, `reading ${file.name}`));
      await openMesh(mesh, file.name, "upload");
    } finally {
      showSampleChoice();
    }
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

  function setUp(up, source = "user") {
    store.set({ up, upSource: source });
    view.setUp(axisVector(up));
  }

  async function downloadGlb() {
    const blob = await withProgress("Encoding GLB…", () => api.meshGlb(state.vertices,
      state.faces));
    const url = URL.createObjectURL(blob);
    const a = document.createElement("a");
    a.href = url;
    a.download = downloadName(state.name);
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    return blob.size;
  }

  store.subscribe(["up"], (s) => { $("up-axis").value = s.up; });
  store.subscribe(["topo"], drawMesh);
  store.subscribe(["topo", "sizeLimits"], drawLimits);
  store.subscribe(["name", "topo", "handles", "lastSolveMs", "up", "upSource"], drawStatus);
  $("sample-select").addEventListener("change", (event) => {
    if (event.target.value) action(loadSample)(event.target.value);
  });
  onFileChosen($("mesh-file"), openUpload);
  $("download-glb").addEventListener("click", action(downloadGlb));
  $("wireframe").addEventListener("change", (event) => view.setWireframe(event.target.checked));
  $("grid-toggle").addEventListener("change", (event) => view.setHelpers(event.target.checked));
  $("up-axis").addEventListener("change", (event) => {
    if (state.vertices) setUp(event.target.value);
  });
  $("fit-view").addEventListener("click", () => state.vertices && view.frame({ keep: true }));
  $("reset-view").addEventListener("click", () => state.vertices && view.frame());
  return { openMesh, loadSample, openUpload, loadSampleList, setUp, downloadGlb };
}
