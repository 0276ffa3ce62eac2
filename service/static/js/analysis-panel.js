// The Mesh panel's integrability report: computed in the worker when a shape opens, drawn
// as a verdict in words and a table (defects, loops, topology, the worst vertices).

import { describe } from "./api.js";
import { shownDefects } from "./color-view.js";
import { DEFECT_LABELS, badge, fmt, loopsText, maxOf, num, setStats } from "./format.js";
import { withProgress } from "./progress.js";
import { state, store } from "./store.js";

const $ = (id) => document.getElementById(id);
const ROUND_OFF = 1e-12;  // a max defect below this is floating-point noise

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

function drawIntegrability(s) {
  const r = s.integrability;
  const verdict = $("integrability-summary");
  $("show-defect").disabled = !r;
  if (!r) {
    const failed = s.analysisError;
    verdict.className = failed ? "verdict bad" : "verdict";
    verdict.textContent = !s.topo ? "Open a mesh to see whether its forms are integrable."
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
    worst.append(num(`v${v}: ${fmt(r[s.defectPart][v], 2)}`));
  });
  const parts = Object.entries(DEFECT_LABELS).map(([key, label]) => [
    `${label} vertex defect (max)`, num(`${fmt(maxOf(r[key]), 3)} rad`),
    key === s.defectPart ? "selected" : ""]);
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
  const rebuiltFrom = s.source === "reconstruction" ? s.reconstruction?.integrability : null;
  $("integrability-note").textContent = r.integrable && rebuiltFrom && !rebuiltFrom.integrable
    ? "This rebuilt surface has exact forms of its own; the colours show the defects of the "
      + "forms it was rebuilt from (Rebuild, 4), which do not fit."
    : r.integrable
    ? "A surface with exactly these edge lengths and angles exists (this one), so there is "
      + "nothing to colour. To see forms that do not fit, open Rebuild (4) and scale the angles."
    : "No surface has exactly these forms: the colours show where they fail, and a "
      + "reconstruction is the closest compromise.";
}

/** The analysis panel; `inWorker(kind, args, label)` runs a worker call. Returns
 * `analyze()`: the report of the shape on screen, into the state. */
export function installAnalysisPanel({ inWorker }) {
  let run = 0;
  store.subscribe(["topo", "integrability", "analysisError", "defectPart", "reconstruction"],
    drawIntegrability);
  $("show-defect").addEventListener("click", () => store.set({ colorMode: "defect" }));
  for (const input of document.querySelectorAll('input[name="defect-part"]')) {
    input.addEventListener("change", () => store.set({ defectPart: input.value,
      ...(state.integrability ? { colorMode: "defect" } : {}) }));
  }

  return async function analyze() {
    const mine = ++run;
    let result;
    try {
      result = await withProgress("Integrability report…", () => inWorker("analyze",
        { vertices: state.vertices, faces: state.faces }, "computing the integrability report"));
    } catch (err) {
      if (mine !== run) throw err;
      store.set({ forms: null, integrability: null,
        analysisError: err?.name === "AbortError" ? null : describe(err) });
      throw err;
    }
    if (mine !== run) return;  // another mesh (or answer) was shown meanwhile
    // Colours only where there is something to see: exact forms are plain. A rebuilt
    // surface is coloured by the forms it was rebuilt from (color-view.js shownDefects).
    const shown = shownDefects({ ...state, integrability: result.integrability }).report;
    store.set({ forms: result.forms, integrability: result.integrability,
      colorMode: shown.integrable ? "plain" : "defect" });
  };
}
