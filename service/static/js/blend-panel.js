// The Blend panel: 2 to 4 shapes of the mesh on screen (the shape as loaded, shapes taken
// from the screen after a deformation, or mesh files with the same faces), one weight
// slider per shape after the first (the first takes 1 - the others: blends are affine, and
// weights outside [0, 1] extrapolate), a live blend of the weights (POST /v1/blend), and
// the sequence from the first shape to those weights played as the service's animated GLB
// (each row a morph target, an animation), loaded with three.js's GLTFLoader and driven
// by an AnimationMixer, the view following its morph weights. A blend's row warnings (the
// answer's top-level `warnings`, each with its `row`: docs/shape-space.md#command-line-and-
// client) are listed under its statistics.

import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { showAnswerWarnings } from "./answer-warnings.js";
import * as api from "./api.js";
import { fmt, pct, setStats } from "./format.js";
import { rows3 } from "./mesh.js";
import { action, jobProgress, onFileChosen, withProgress } from "./progress.js";
import { state, store } from "./store.js";

const $ = (id) => document.getElementById(id);
export const MAX_SHAPES = 4;
export const SEQUENCE_ROWS = 24;

/** The weights of every shape: the sliders' for shapes 2.., the first gets the rest. */
function weightsOf(shapes) {
  const others = shapes.slice(1).map((_, k) => Number($(`blend-w${k + 1}`)?.value ?? 0));
  return [1 - others.reduce((a, b) => a + b, 0), ...others];
}

function drawShapes(s) {
  const list = $("blend-shapes");
  list.replaceChildren(...s.blendShapes.map((shape, k) => {
    const item = document.createElement("li");
    const label = document.createElement("span");
    label.textContent = `${k + 1}. ${shape.name}`;
    item.append(label);
    if (k > 0) {
      const slider = document.createElement("input");
      Object.assign(slider, { type: "range", id: `blend-w${k}`, min: "-1", max: "2",
        step: "0.05", value: String(shape.weight ?? 0) });
      slider.setAttribute("aria-label", `weight of shape ${k + 1}`);
      item.append(slider);
    }
    const value = document.createElement("output");
    value.id = `blend-v${k}`;
    item.append(value);
    return item;
  }));
  drawWeights();
  const ready = s.blendShapes.length >= 2;
  $("blend-apply").disabled = !ready;
  $("blend-play").disabled = !ready;
  $("blend-download").disabled = !ready;
  $("blend-add").disabled = !s.vertices || s.blendShapes.length >= MAX_SHAPES;
  $("blend-file-button").classList.toggle("disabled", !s.vertices
    || s.blendShapes.length >= MAX_SHAPES);
}

function drawWeights() {
  const weights = weightsOf(state.blendShapes);
  weights.forEach((w, k) => { if ($(`blend-v${k}`)) $(`blend-v${k}`).textContent = fmt(w, 2); });
}

function drawReport(s) {
  const r = s.blendReport;
  setStats("blend-stats", r ? [
    ["Rows", String(r.rows)],
    ["Length error vs the blended forms (mean, worst row)", pct(r.length)],
    ["Angle error (mean, worst row)", `${fmt(r.angle)} rad`],
  ] : []);
  showAnswerWarnings("blend-warnings", r ? rowWarnings(r) : []);
}

/** A blend's warnings for the list: each names its row where the blend has several. */
function rowWarnings(report) {
  return report.warnings.map((w) => (report.rows > 1
    ? { ...w, message: `Row ${w.row + 1}: ${w.message}` } : w));
}

/** The Blend panel over the 3D `view`; returns its actions (for the tests). */
export function installBlendPanel({ view }) {
  let player = null;  // {mixer, mesh, base, targets, clip, clock, frame}

  function addShape(name, vertices) {
    store.set({ blendShapes: [...state.blendShapes, { name, vertices: vertices.slice() }] });
  }

  function addOnScreen() {
    const count = state.blendShapes.length;
    addShape(count === 0 ? `${state.name} (as shown)` : `shape ${count + 1}`, state.vertices);
  }

  async function addFile(file) {
    const mesh = await withProgress("Reading mesh…", () => api.readMeshFile(file, file.name));
    const faces = mesh.faces.flat();
    if (faces.length !== state.faces.length || faces.some((f, i) => f !== state.faces[i])) {
      throw new api.ApiError({ title: "Not the same mesh", status: 0, detail: `${file.name} `
        + "has other faces than the mesh on screen: a blend needs one connectivity." },
      "blend");
    }
    if (!state.blendShapes.length) addOnScreen();
    addShape(file.name, Float64Array.from(mesh.vertices.flat()));
  }

  function body(rows) {
    return { shapes: state.blendShapes.map((shape) => rows3(shape.vertices)),
      faces: rows3(state.faces), weights: rows };
  }

  /** Rows from the first shape (t = 0) to the sliders' weights (t = 1). */
  function sequenceRows(count = SEQUENCE_ROWS) {
    const target = weightsOf(state.blendShapes);
    return Array.from({ length: count }, (_, i) => {
      const t = i / (count - 1);
      return target.map((w, k) => t * w + (1 - t) * (k === 0 ? 1 : 0));
    });
  }

  function show(vertices) {
    view.updatePositions(vertices);
  }

  function summarize(result) {
    const reports = result.reports;
    const worst = (key) => Math.max(...reports.map((r) => r.form_error[key].mean));
    store.set({ blendReport: { rows: reports.length, length: worst("length_error"),
      angle: worst("angle_error"), warnings: result.warnings ?? [] } });
  }

  /** The blend of the sliders' weights, shown (one row, synchronous). */
  async function apply() {
    stop();
    // A mesh too large for a synchronous answer (413 use-a-job) is blended as a job.
    const result = await withProgress("Blending…", (signal) => api.postJsonOrJob("blend",
      "/v1/blend", body([weightsOf(state.blendShapes)]),
      { signal, onProgress: jobProgress("Blending") }), { cancellable: true });
    const vertices = Float64Array.from(result.vertices[0].flat());
    show(vertices);
    summarize(result);
    store.set({ blendFrame: -1 });
    return vertices;
  }

  async function sequenceGlb() {
    const times = sequenceRows().map((_, i) => i / SEQUENCE_ROWS);
    const response = await api.request("/v1/blend", { json: { ...body(sequenceRows()), times },
      accept: "model/gltf-binary" });
    return response.arrayBuffer();
  }

  /** Fetch the sequence as an animated GLB and play it once, the view following it. */
  async function play() {
    stop();
    const data = await withProgress("Blending the sequence…", () => sequenceGlb());
    const gltf = await new GLTFLoader().parseAsync(data, "");
    let mesh = null;
    gltf.scene.traverse((object) => { if (object.isMesh && !mesh) mesh = object; });
    const clip = gltf.animations[0];
    const mixer = new THREE.AnimationMixer(mesh);
    const playing = mixer.clipAction(clip);
    playing.setLoop(THREE.LoopOnce);
    playing.clampWhenFinished = true;
    playing.play();
    const geometry = mesh.geometry;
    player = { mixer, mesh, clip, clock: new THREE.Clock(), frame: 0,
      base: geometry.getAttribute("position").array,
      targets: geometry.morphAttributes.position.map((a) => a.array),
      relative: geometry.morphTargetsRelative };
    store.set({ blendFrame: 0, blendPlaying: true });
    tick();
    return { rows: player.targets.length, duration: clip.duration };
  }

  /** The morphed positions of the player's mesh: base + sum_k w_k target_k. */
  function morphed() {
    const { base, targets, mesh, relative } = player;
    const out = Float64Array.from(base);
    mesh.morphTargetInfluences.forEach((w, k) => {
      if (!w) return;
      const target = targets[k];
      for (let i = 0; i < out.length; i += 1) {
        out[i] += w * (relative ? target[i] : target[i] - base[i]);
      }
    });
    return out;
  }

  function tick() {
    if (!player) return;
    player.mixer.update(player.clock.getDelta());
    show(morphed());
    player.frame += 1;
    const time = player.mixer.time;
    store.set({ blendFrame: player.frame, blendTime: time });
    if (time >= player.clip.duration) {
      store.set({ blendPlaying: false });
      player = null;
      return;
    }
    requestAnimationFrame(tick);
  }

  function stop() {
    player = null;
    store.set({ blendPlaying: false });
  }

  async function download() {
    const blob = new Blob([await withProgress("Encoding the animation…", () => sequenceGlb())],
      { type: "model/gltf-binary" });
    const url = URL.createObjectURL(blob);
    const a = document.createElement("a");
    a.href = url;
    a.download = `${(state.name || "mesh").replace(/\.[^.]+$/, "")}-blend.glb`;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    return blob.size;
  }

  function clear() {
    stop();
    store.set({ blendShapes: [], blendReport: null });
    if (state.vertices) show(state.vertices);
  }

  store.subscribe(["blendShapes", "vertices"], drawShapes);
  store.subscribe(["blendReport"], drawReport);
  store.subscribe(["topo"], () => { if (state.blendShapes.length) clear(); });
  $("blend-shapes").addEventListener("input", drawWeights);
  $("blend-shapes").addEventListener("change", action(apply));
  $("blend-add").addEventListener("click", () => addOnScreen());
  onFileChosen($("blend-file"), addFile);
  $("blend-apply").addEventListener("click", action(apply));
  $("blend-play").addEventListener("click", action(play));
  $("blend-download").addEventListener("click", action(download));
  $("blend-clear").addEventListener("click", clear);
  return { addOnScreen, addFile, apply, play, stop, download, sequenceRows,
    setWeight(k, w) {
      $(`blend-w${k}`).value = String(w);
      drawWeights();
    },
    weights: () => weightsOf(state.blendShapes),
    shown: () => Array.from(view.mesh.geometry.getAttribute("position").array) };
}
