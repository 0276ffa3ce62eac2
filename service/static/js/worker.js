// The page's heavy lifting off the main thread: reading a mesh file through the service
// (POST /v1/mesh), the JSON of big answers, the edge topology and forms, and the
// integrability report (POST /v1/forms, then POST /v1/integrability, both with binary bodies:
// application/vnd.ffs.arrays). Typed arrays go back to the page transferred, not copied, so
// opening a 100K-face mesh never blocks the page for long.
//
// Messages: {id, kind, args} -> {id, accepted: true} at once, then {id, result} or
// {id, error: {problem, context} | {name, message}}; {ready: true} once this module listens,
// {alive: true} every PULSE_MS while a call is in progress (js/worker-client.js waits for the
// first and bounds the silences).

import { ApiError, arraysBody, readMeshFile, request } from "./api.js";
import { setApiKey } from "./auth.js";
import { prepareMesh, preparedBuffers } from "./mesh.js";

const F64 = ["vertex_defect", "gauss_defect", "codazzi_defect"];

function flatRows(rows, Type, width) {
  const out = new Type(rows.length * width);
  for (let i = 0; i < rows.length; i++) {
    for (let k = 0; k < width; k++) out[width * i + k] = rows[i][k];
  }
  return out;
}

const handlers = {
  /** A mesh file (Blob) -> the prepared mesh and the service's reading report. */
  async readMesh({ file, name }) {
    const mesh = await readMeshFile(file, name);
    const prepared = prepareMesh(mesh.vertices, mesh.faces);
    return [{ ...prepared, report: mesh.report }, preparedBuffers(prepared)];
  },

  /** Flat vertices and faces -> forms (typed) and the integrability report (per-vertex
   * defects as Float64Array). */
  async analyze({ vertices, faces }) {
    const doc = await (await request("/v1/forms", arraysBody({}, {
      vertices: [vertices, [vertices.length / 3, 3]], faces: [faces, [faces.length / 3, 3]] })))
      .json();
    const forms = { faces: flatRows(doc.faces, Uint32Array, 3),
      edges: flatRows(doc.edges, Uint32Array, 2),
      lengths: Float64Array.from(doc.lengths), angles: Float64Array.from(doc.angles) };
    const report = await (await request("/v1/integrability", arraysBody({}, {
      faces: [forms.faces, [forms.faces.length / 3, 3]],
      edges: [forms.edges, [forms.edges.length / 2, 2]],
      lengths: [forms.lengths, [forms.lengths.length]],
      angles: [forms.angles, [forms.angles.length]] }))).json();
    for (const key of F64) report[key] = Float64Array.from(report[key]);
    const buffers = [forms.faces.buffer, forms.edges.buffer, forms.lengths.buffer,
      forms.angles.buffer, ...F64.map((k) => report[k].buffer)];
    return [{ forms, integrability: report }, buffers];
  },
};

const PULSE_MS = 5000;
let working = 0, pulse = null;

self.onmessage = async ({ data: { id, kind, args } }) => {
  setApiKey(args?.apiKey);  // the page's key (js/auth.js): no sessionStorage in a worker
  self.postMessage({ id, accepted: true });
  if (!working++) pulse = setInterval(() => self.postMessage({ alive: true }), PULSE_MS);
  try {
    const [result, transfer] = await handlers[kind](args);
    self.postMessage({ id, result }, transfer);
  } catch (err) {
    const error = err instanceof ApiError ? { problem: err.problem, context: err.context }
      : { name: err?.name ?? "Error", message: err?.message ?? String(err) };
    self.postMessage({ id, error });
  } finally {
    if (!--working) clearInterval(pulse);
  }
};
self.postMessage({ ready: true });
