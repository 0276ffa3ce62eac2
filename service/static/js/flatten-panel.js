// The Flatten panel: the mesh's flat layout (a parameterize job), shown beside the 3D view
// with its flipped faces in red, its distortion figures, and the checkerboard on the mesh.

import { showAnswerWarnings } from "./answer-warnings.js";
import * as api from "./api.js";
import { badge, deg, fmt, pct, setStats } from "./format.js";
import { rows3 } from "./mesh.js";
import { action, jobProgress, withProgress } from "./progress.js";
import { state, store } from "./store.js";

const $ = (id) => document.getElementById(id);

function drawAvailability(s) {
  $("flatten").disabled = !s.topo || s.closed;
  $("flatten-note").textContent = s.topo && s.closed
    ? "This mesh is closed: a flat layout needs a boundary. Open a mesh with a hole (the Face "
      + "sample is a disk)." : "";
}

function drawLayout(s) {
  const flat = s.flat;
  showAnswerWarnings("flatten-warnings", flat?.report?.warnings);
  if (!flat) {
    setStats("flatten-stats", []);
    return;
  }
  const r = flat.report;
  const flips = flat.flipped.length;
  $("flip-note").textContent = flips ? `${flips} flipped face(s) in red` : "no flipped faces";
  $("flip-note").className = `flip-note${flips ? " bad" : ""}`;
  setStats("flatten-stats", [
    ["Flipped faces", badge(flips === 0, "0", String(flips))],
    ["Length change (mean)", pct(r.length_change_summary.mean)],
    ["Length change (max)", pct(r.length_change_summary.max)],
    ["Angle distortion (max)", deg(r.angle_distortion_summary.max)],
    ["Area ratio − 1 (rms)", fmt(r.area_ratio_summary.rms)],
  ]);
}

/** The Flatten panel over the 3D `view` and the 2D `flatView`; returns `flatten()`. */
export function installFlattenPanel({ view, flatView }) {
  function hideFlat() {
    $("view-flat").hidden = true;
    $("viewport").classList.remove("split");
    if (state.colorMode === "checker") store.set({ colorMode: "plain" });
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
    view.resize();
    view.frame({ keep: true });
    store.set({ flat: { uv, flipped: result.flipped_faces, report: result.report, texcoords },
      colorMode: "checker" });
  }

  store.subscribe(["topo", "closed"], drawAvailability);
  store.subscribe(["flat"], drawLayout);
  store.subscribe(["topo"], () => hideFlat());  // a new mesh has no layout yet
  $("flatten").addEventListener("click", action(flatten));
  $("close-flat").addEventListener("click", () => {
    hideFlat();
    view.resize();
    view.frame({ keep: true });
  });
  return { flatten };
}
