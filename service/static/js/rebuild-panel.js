// The Rebuild panel: a surface rebuilt from a forms document (an uploaded file, or the
// shown mesh's forms with its angles scaled) by a reconstruct job, checked for
// integrability, placed on the mesh it came from, with the refined and the linear answers
// side by side (their residuals) and a switch between them.

import { showAnswerWarnings } from "./answer-warnings.js";
import * as api from "./api.js";
import { badge, deg, fmt, loopsText, maxOf, num, pct, setStats } from "./format.js";
import { flatten3, forms as meshForms, rigidAlign } from "./mesh.js";
import { action, jobProgress, onFileChosen, withProgress } from "./progress.js";
import { state, store } from "./store.js";

const $ = (id) => document.getElementById(id);
const FORM_KEYS = ["faces", "edges", "lengths", "angles"];
/** What a forms document may also carry (POST /v1/forms of a non-manifold, welded or
 * multi-part mesh): the cut's vertex map, the weld map and each part's placement, passed
 * on so that the rebuilt surface is the file's, in place. */
const OPTIONAL_FORM_KEYS = ["vertex_map", "weld_map", "placement"];

/** The reconstruct job's input: options.refine null (the default) refines when the linear
 * answer needs it; false asks for the linear least-squares answer. */
function reconstructInput(input, refine) {
  return refine === undefined ? input : { ...input, options: { refine } };
}

/** An answer's vertices (rows) as shown: flat, and on the mesh the forms came from. */
function placedAnswer(rec, rows) {
  const vertices = flatten3(rows);
  return rec.alignTo && rec.alignTo.length === vertices.length
    ? rigidAlign(vertices, rec.alignTo) : vertices;
}

/** A residual summary of report.refinement ("before"/"after"): nested summaries
 * ({length_error: {mean, max}, ...}) or flat keys (length_error_mean, ...). */
function residual(r, kind, stat) {
  return r?.[kind]?.[stat] ?? r?.[`${kind}_${stat}`];
}

/** The residual table: length and angle errors of the linear and the refined answer. */
function drawResiduals(f) {
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

function drawReconstruction(s) {
  const rec = s.reconstruction;
  $("compare-row").hidden = !rec?.refinement?.refined;
  showAnswerWarnings("forms-warnings", rec?.report?.warnings);
  if (!rec) {
    setStats("forms-stats", []);
    drawResiduals(null);
    $("forms-note").textContent = "";
    return;
  }
  const r = rec.report || {};
  const f = rec.refinement;
  const seconds = r.timings ? Object.values(r.timings).reduce((a, b) => a + b, 0) : null;
  const rows = [
    ["Rebuilt", num(`${(s.vertices.length / 3).toLocaleString("en")} vertices`)],
    ["Forms integrable", badge(rec.integrability.integrable)],
    ["Forms' vertex defect (max)", num(`${fmt(maxOf(rec.integrability.vertex_defect))} rad`)],
    ["Forms' global loops", loopsText(rec.integrability), "wrap"],
    ["Method", r.solve_path === "tree-integration" ? "exact integration" : "least squares"],
  ];
  if (f?.refined) {
    rows.push(["Showing", rec.showing === "refined" ? "refined answer" : "linear answer"]);
    rows.push(["Refinement", num(`${f.iterations} steps, ${(1000 * f.seconds).toFixed(0)} ms`
      + (f.converged ? "" : " (not converged)"))]);
    if (f.outcome_text) rows.push(["Outcome", f.outcome_text, "wrap"]);
  } else if (seconds !== null) {
    rows.push(["Solve time", num(`${(1000 * (seconds + (f?.seconds ?? 0))).toFixed(0)} ms`)]);
  }
  setStats("forms-stats", rows);
  drawResiduals(f);
  document.querySelector(`input[name="answer"][value="${rec.showing}"]`).checked = true;
  $("forms-note").textContent = f?.refined && rec.showing === "linear"
    ? "The linear answer shown here can shrink or crumple a surface whose forms do not fit; "
      + "the refined one is the nearest surface to the forms. Switch to Refined to see it."
    : f?.refined
    ? "The linear answer can shrink or crumple a surface whose forms do not fit; the refined "
      + "one shown here is the nearest surface to the forms. Switch to Linear to compare."
    : rec.integrability.integrable ? "The forms fit together: this is the surface they describe."
      : "The forms do not fit together: this is the least-squares compromise.";
}

/** A forms document with plain arrays (faces, edges as rows) from typed or nested forms,
 * the dihedral angles scaled by `scale` (and kept in [-pi, pi]). */
function formsInput(f, scale = 1) {
  const rows = (a, w) => (Array.isArray(a) ? a
    : Array.from({ length: a.length / w }, (_, i) => Array.from(a.subarray(w * i, w * i + w))));
  return { faces: rows(f.faces, 3), edges: rows(f.edges, 2), lengths: Array.from(f.lengths),
    angles: Array.from(f.angles, (a) => Math.max(-Math.PI, Math.min(Math.PI, a * scale))) };
}

function checkFormsDocument(doc, source) {
  if (!doc || typeof doc !== "object" || Array.isArray(doc)) {
    throw new api.ApiError({ title: "Not a forms document",
      detail: `${source}: expected a JSON object with ${FORM_KEYS.join(", ")} (the output of POST /v1/forms)` });
  }
  const missing = FORM_KEYS.filter((k) => !(k in doc));
  if (missing.length) {
    throw new api.ApiError({ title: "Not a forms document",
      detail: `${source}: missing ${missing.join(", ")}; upload the output of POST /v1/forms` });
  }
}

/** The Rebuild panel. `openMesh` (Mesh panel) shows the answer; `analyze` (analysis
 * panel) reports on the answer shown. */
export function installRebuildPanel({ view, openMesh, analyze }) {
  /**
   * Rebuild a surface from a forms document and show it. `from` is the mesh the forms came
   * from, when there is one ({vertices, up, upSource}): the answer is moved rigidly onto it
   * and keeps its up axis (the service's answer has an arbitrary placement).
   */
  async function reconstructForms(doc, name, source = name, from = null) {
    checkFormsDocument(doc, source);
    const input = Object.fromEntries([...FORM_KEYS, ...OPTIONAL_FORM_KEYS]
      .filter((k) => doc[k] != null).map((k) => [k, doc[k]]));
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
    store.set({ tab: "forms" });
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
    store.set({ handles: [], active: null, selection: [] });  // closes the deformation
    view.updatePositions(vertices);
    view.buildHelpers();  // the camera stays: the two answers are seen at the same scale
    store.set({ vertices, rest: vertices.slice(), deformed: false, distortion: null, undo: [],
      redo: [], reference: meshForms(vertices, state.faces, state.topo), forms: null,
      integrability: null });
    store.changed("reconstruction");
    await analyze();
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

  async function bendForms() {
    const box = $("angle-scale");
    const scale = box.value.trim() === "" ? NaN : Number(box.value);
    if (!Number.isFinite(scale)) throw new api.ApiError({ title: "Invalid angle scale",
      detail: "the Angles × box is empty or not a number: enter a number, e.g. 0.8" });
    if (!state.forms) return;
    const stem = state.name.replace(/ \(.*\)$/, "");
    await reconstructForms(formsInput(state.forms, scale), `${stem} (angles × ${scale})`, undefined,
      { vertices: state.vertices, up: state.up, upSource: state.upSource });
  }

  store.subscribe(["reconstruction"], drawReconstruction);
  store.subscribe(["forms"], (s) => { $("bend-forms").disabled = !s.forms; });
  onFileChosen($("forms-file"), openFormsFile);
  $("bend-forms").addEventListener("click", action(bendForms));
  for (const input of document.querySelectorAll('input[name="answer"]')) {
    input.addEventListener("change", action(() => showAnswer(input.value)));
  }
  return { showAnswer };
}
