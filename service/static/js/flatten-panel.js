// The Flatten panel: the mesh's flat layout (a parameterize job), shown beside the 3D view
// with its flipped faces in red, its distortion figures, and the checkerboard on the mesh.
// A mesh that is not one good chart (closed, handles, several parts) comes back as an atlas:
// charts cut along seams and packed; the 3D view then shows the atlas's checkerboard on a
// copy of the mesh whose seam vertices are duplicated (one uv each).

import * as THREE from "three";
import { showAnswerWarnings } from "./answer-warnings.js";
import * as api from "./api.js";
import { badge, deg, fmt, pct, setStats } from "./format.js";
import { rows3 } from "./mesh.js";
import { action, jobProgress, withProgress } from "./progress.js";
import { CHECKER_REPEAT } from "./render-view.js";
import { state, store } from "./store.js";

const $ = (id) => document.getElementById(id);

function drawAvailability(s) {
  $("flatten").disabled = !s.topo;
  $("flatten-note").textContent = s.topo && s.closed
    ? "This mesh is closed: it is cut along seams into charts, each flattened and packed "
      + "into the unit square (an atlas)." : "";
}

/** The unique undirected edges [i, j] of flat faces (Uint32Array(3m)), as Uint32Array(2E). */
function uvEdges(faces) {
  const seen = new Set(), out = [];
  for (let t = 0; t < faces.length; t += 3) {
    for (let k = 0; k < 3; k++) {
      const a = faces[t + k], b = faces[t + (k + 1) % 3];
      const i = Math.min(a, b), j = Math.max(a, b), key = i * 4294967296 + j;
      if (!seen.has(key)) {
        seen.add(key);
        out.push(i, j);
      }
    }
  }
  return Uint32Array.from(out);
}

/** The 3D mesh with seam vertices duplicated and the atlas's checkerboard (one per view). */
function atlasMesh(view, atlas) {
  const k = atlas.uvVertex.length;
  const positions = new Float32Array(3 * k), uv = new Float32Array(2 * k);
  for (let i = 0; i < k; i++) {
    const v = atlas.uvVertex[i];
    positions.set(state.vertices.subarray(3 * v, 3 * v + 3), 3 * i);
    // 8 checker cells across the unit square per CHECKER_REPEAT: finer than one chart.
    uv[2 * i] = atlas.texcoords[2 * i] * CHECKER_REPEAT * 8;
    uv[2 * i + 1] = atlas.texcoords[2 * i + 1] * CHECKER_REPEAT * 8;
  }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  geometry.setAttribute("uv", new THREE.BufferAttribute(uv, 2));
  geometry.setIndex(new THREE.BufferAttribute(atlas.uvFaces, 1));
  geometry.computeVertexNormals();
  const mesh = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial({ map: view.checker,
    roughness: 0.62, metalness: 0.0, side: THREE.DoubleSide }));
  mesh.name = "atlas";
  return mesh;
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
  const atlas = r.atlas || {};
  setStats("flatten-stats", [
    ["Charts", String(atlas.charts ?? 1)],
    ...(atlas.charts > 1 ? [["Seam length", fmt(atlas.seam_length)],
      ["Packing efficiency", pct(atlas.packing_efficiency)]] : []),
    ["Flipped faces", badge(flips === 0, "0", String(flips))],
    ["Length change (mean)", pct(r.length_change_summary.mean)],
    ["Length change (max)", pct(r.length_change_summary.max)],
    ["Angle distortion (max)", deg(r.angle_distortion_summary.max)],
    ["Area ratio − 1 (rms)", fmt(r.area_ratio_summary.rms)],
  ]);
}

/** The Flatten panel over the 3D `view` and the 2D `flatView`; returns `flatten()`. */
export function installFlattenPanel({ view, flatView }) {
  let overlay = null;
  function dropOverlay() {
    if (overlay) {
      view.scene.remove(overlay);
      overlay.geometry.dispose();
      overlay.material.dispose();
      overlay = null;
    }
    if (view.mesh) view.mesh.visible = true;
    view.request();
  }

  function drawOverlay(s) {
    const show = s.colorMode === "checker" && s.flat?.atlas && s.vertices === s.flat.vertices;
    if (!show) {
      dropOverlay();
      return;
    }
    if (!overlay) {
      overlay = atlasMesh(view, s.flat.atlas);
      view.scene.add(overlay);
    }
    view.mesh.visible = false;
    view.request();
  }

  function hideFlat() {
    $("view-flat").hidden = true;
    $("viewport").classList.remove("split");
    dropOverlay();
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
    const charts = result.report.atlas?.charts ?? 1;
    const single = charts === 1 && result.uv.length * 3 === state.vertices.length;
    const uvFaces = single ? state.faces : Uint32Array.from(result.uv_faces.flat());
    $("view-flat").hidden = false;
    $("viewport").classList.add("split");
    await new Promise((resolve) => requestAnimationFrame(resolve));
    const shown = flatView.show(uv, uvFaces, single ? state.topo.edges : uvEdges(uvFaces),
      result.flipped_faces);
    view.resize();
    view.frame({ keep: true });
    dropOverlay();
    const atlas = single ? null : { uvFaces, uvVertex: Uint32Array.from(result.uv_vertex),
      texcoords: Float64Array.from(result.texcoords.flat()),
      faceChart: Uint32Array.from(result.face_chart) };
    store.set({ flat: { uv, flipped: result.flipped_faces, report: result.report,
      texcoords: single ? shown : null, atlas, vertices: state.vertices },
    colorMode: "checker" });
  }

  store.subscribe(["topo", "closed"], drawAvailability);
  store.subscribe(["flat"], drawLayout);
  store.subscribe(["flat", "colorMode", "vertices"], drawOverlay);
  store.subscribe(["topo"], () => hideFlat());  // a new mesh has no layout yet
  $("flatten").addEventListener("click", action(flatten));
  $("close-flat").addEventListener("click", () => {
    hideFlat();
    view.resize();
    view.frame({ keep: true });
  });
  return { flatten };
}
