// The service's public HTTP API as used by the page. Every failure becomes an ApiError that
// carries the RFC 9457 problem document (or one made up for network errors), so the page can
// show a readable message; nothing is swallowed here. A 401 on the page asks for an API key
// (js/auth.js) and sends the request again with it.

import { askForKey, authHeaders, canAsk } from "./auth.js";

export class ApiError extends Error {
  constructor(problem, context = "") {
    super(problem.detail || problem.title || "request failed");
    this.name = "ApiError";
    this.problem = problem;
    this.status = problem.status ?? 0;
    this.context = context;
  }
}

async function problemFrom(response, context) {
  const type = response.headers.get("content-type") || "";
  let problem = null;
  if (type.includes("json")) {
    try {
      problem = await response.json();
    } catch {
      problem = null;
    }
  }
  if (!problem || typeof problem !== "object") {
    const text = await response.text().catch(() => "");
    problem = { title: response.statusText || "HTTP error", detail: text.slice(0, 300) };
  }
  problem.status ??= response.status;
  return new ApiError(problem, context);
}

/** Milliseconds a request may take, answer included, before the page gives up on it (the
 * service's own bounds are shorter: FFS_REQUEST_TIMEOUT, FFS_BODY_TIMEOUT). */
export const REQUEST_TIMEOUT_MS = 300_000;

/** fetch() with problem-document errors. `json` or `form` is the body, or `body` with its
 * `contentType` (e.g. from arraysBody). */
export async function request(path, { method = "POST", json, form, body, contentType,
  accept = "application/json", signal, keepalive = false, timeoutMs = REQUEST_TIMEOUT_MS } = {}) {
  const headers = { Accept: accept };
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  } else if (form) {
    body = form;
  } else if (contentType) {
    headers["Content-Type"] = contentType;
  }
  const context = `${method} ${path}`;
  const bound = AbortSignal.timeout(timeoutMs);
  let response;
  try {
    for (;;) {
      response = await fetch(path, { method, headers: { ...headers, ...authHeaders() }, body,
        keepalive, signal: signal ? AbortSignal.any([signal, bound]) : bound });
      if (response.status !== 401 || !canAsk()) break;
      const problem = await problemFrom(response, context);
      if (!await askForKey(problem.problem)) throw problem;  // cancelled: the 401 stands
    }
  } catch (err) {
    if (err instanceof ApiError) throw err;
    if (err.name === "TimeoutError") {
      throw new ApiError({ title: "No answer", status: 0,
        detail: `${context}: the service did not answer within ${timeoutMs / 1000} s.` }, context);
    }
    if (err.name === "AbortError") throw err;
    throw new ApiError({ title: "Network error", status: 0,
      detail: `${context} failed: ${err.message}. Is the service running?` }, context);
  }
  if (!response.ok) throw await problemFrom(response, context);
  return response;
}

// ------------------------------------------------------------------------ binary bodies

/** The operations' binary body (docs/service.md, "Binary bodies"): the large arrays as raw
 * little-endian bytes behind a JSON header, so nothing is printed or parsed number by
 * number. The synchronous operations take it; jobs and sessions take JSON only. */
export const ARRAYS_TYPE = "application/vnd.ffs.arrays";

const DTYPES = new Map([[Float64Array, ["<f8", "setFloat64"]], [Float32Array, ["<f4", "setFloat32"]],
  [Int32Array, ["<i4", "setInt32"]], [Uint32Array, ["<u4", "setUint32"]]]);
const LITTLE_ENDIAN = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;
const padded = (n) => Math.ceil(n / 8) * 8;

/**
 * `{body, contentType}` of a binary body, to spread into request() options. `params` are the
 * body's other (small) fields; `arrays` maps a name to [typed array (flat, C order), shape],
 * e.g. {vertices: [Float64Array(3n), [n, 3]], faces: [Uint32Array(3m), [m, 3]]}.
 */
export function arraysBody(params, arrays) {
  const meta = {};
  for (const [name, [data, shape]] of Object.entries(arrays)) {
    const dtype = DTYPES.get(data.constructor);
    if (!dtype) throw new TypeError(`${name}: no binary dtype for ${data.constructor.name}`);
    if (shape.reduce((a, b) => a * b, 1) !== data.length) {
      throw new RangeError(`${name}: ${data.length} values do not fill the shape [${shape}]`);
    }
    meta[name] = { dtype: dtype[0], shape };
  }
  const header = new TextEncoder().encode(JSON.stringify({ ...params, arrays: meta }));
  let size = padded(8 + header.length);
  for (const [data] of Object.values(arrays)) size += padded(data.byteLength);
  const bytes = new Uint8Array(size);  // zero-filled: the padding
  const view = new DataView(bytes.buffer);
  bytes.set([0x46, 0x46, 0x53, 0x41]);  // "FFSA"
  view.setUint32(4, header.length, true);
  bytes.set(header, 8);
  let offset = padded(8 + header.length);
  for (const [data] of Object.values(arrays)) {
    if (LITTLE_ENDIAN) {
      bytes.set(new Uint8Array(data.buffer, data.byteOffset, data.byteLength), offset);
    } else {
      const setter = DTYPES.get(data.constructor)[1];
      for (let i = 0; i < data.length; i++) view[setter](offset + i * data.BYTES_PER_ELEMENT, data[i], true);
    }
    offset += padded(data.byteLength);
  }
  return { body: bytes, contentType: ARRAYS_TYPE };
}

/**
 * Nested JSON rows (`[[a, b, c], ...]`, or a flat list when `width` is 0) as a typed array
 * and its shape, for arraysBody(); null unless every row has `width` numbers (integers that
 * `Type` holds exactly, for indices). On null the caller sends JSON, so that the service's
 * answer names the element that is wrong, as sent.
 */
export function packRows(rows, width, Type = Float64Array) {
  if (!Array.isArray(rows)) return null;
  const integer = Type !== Float64Array && Type !== Float32Array;
  const low = Type === Uint32Array ? 0 : -(2 ** 31), high = Type === Uint32Array ? 2 ** 32 : 2 ** 31;
  const ok = (x) => typeof x === "number" && (!integer || (Number.isInteger(x) && x >= low && x < high));
  const out = new Type(rows.length * (width || 1));
  for (let i = 0; i < rows.length; i++) {
    const row = rows[i];
    if (width === 0) {
      if (!ok(row)) return null;
      out[i] = row;
      continue;
    }
    if (!Array.isArray(row) || row.length !== width) return null;
    for (let k = 0; k < width; k++) {
      if (!ok(row[k])) return null;
      out[width * i + k] = row[k];
    }
  }
  return [out, width ? [rows.length, width] : [rows.length]];
}

/** A forms document's arrays (faces, edges, lengths, angles; nested rows or flat typed
 * arrays) for arraysBody(), or null when one of them is not well-formed (see packRows). */
export function formsArrays(doc) {
  const pack = (value, width, Type) => (value instanceof Type
    ? [value, width ? [value.length / width, width] : [value.length]]
    : packRows(value, width, Type));
  const arrays = { faces: pack(doc.faces, 3, Uint32Array), edges: pack(doc.edges, 2, Uint32Array),
    lengths: pack(doc.lengths, 0, Float64Array), angles: pack(doc.angles, 0, Float64Array) };
  return Object.values(arrays).every(Boolean) ? arrays : null;
}

export async function getJson(path, options = {}) {
  return (await request(path, { method: "GET", ...options })).json();
}

export async function postJson(path, json, options = {}) {
  return (await request(path, { json, ...options })).json();
}

function fileForm(file, name, fields = {}) {
  const form = new FormData();
  form.append("file", file, name);
  for (const [key, value] of Object.entries(fields)) {
    form.append(key, typeof value === "string" ? value : JSON.stringify(value));
  }
  return form;
}

/** A mesh file read by the service: {vertices, faces, report} in the file's vertex order. */
export async function readMeshFile(file, name) {
  return (await request("/v1/mesh", { form: fileForm(file, name) })).json();
}

/** The mesh (flat Float64Array(3n) vertices, Uint32Array(3m) faces) as a GLB file (Blob). */
export async function meshGlb(vertices, faces) {
  const response = await request("/v1/mesh", { ...arraysBody({}, {
    vertices: [vertices, [vertices.length / 3, 3]], faces: [faces, [faces.length / 3, 3]] }),
  accept: "model/gltf-binary" });
  return response.blob();
}

/** POST a binary body (arraysBody) and return the JSON answer. */
export async function postArrays(path, params, arrays, options = {}) {
  return (await request(path, { ...arraysBody(params, arrays), ...options })).json();
}

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

/**
 * Runs an operation as a job: POST /v1/jobs, polls GET /v1/jobs/{id} (progress goes to
 * `onProgress(status)`), then fetches the JSON result. `cancel.signal` (an AbortController)
 * cancels the job with DELETE.
 */
export async function runJob(operation, input, { color, onProgress, signal } = {}) {
  const response = await request("/v1/jobs", { json: { operation, input,
    ...(color ? { color } : {}) }, signal });
  let status = await response.json();
  const location = response.headers.get("location") || `/v1/jobs/${status.id}`;
  let delay = 50;
  const cancel = () => {
    request(location, { method: "DELETE" }).catch((err) => console.warn("cancel failed", err));
  };
  signal?.addEventListener("abort", cancel, { once: true });
  try {
    while (status.status === "queued" || status.status === "running") {
      onProgress?.(status);
      await sleep(delay);
      delay = Math.min(400, delay * 1.5);
      if (signal?.aborted) throw new DOMException("cancelled", "AbortError");
      status = await getJson(location, { signal });
    }
    onProgress?.(status);
    if (status.status === "failed") {
      throw new ApiError(status.error || { title: "Job failed", detail: `job ${status.id} failed` },
        `job ${operation}`);
    }
    if (status.status === "cancelled") throw new DOMException("cancelled", "AbortError");
    const query = color ? `?color=${encodeURIComponent(color)}` : "";
    return await getJson(`${location}/result${query}`, { signal });
  } finally {
    signal?.removeEventListener("abort", cancel);
  }
}

/** Whether `err` is the service's 413 `use-a-job`: the request would miss the synchronous
 * deadline (FFS_REQUEST_TIMEOUT) and is to be submitted as a job. */
export const isUseAJob = (err) => err instanceof ApiError && err.problem.kind === "use-a-job";

/**
 * POST `json` to the synchronous `path` and return its JSON answer; when the service answers
 * 413 `use-a-job` (a mesh too large for a synchronous answer), the same input runs as a job
 * of `operation` (runJob: progress, cancellation) and its result is returned instead.
 */
export async function postJsonOrJob(operation, path, json, { signal, onProgress } = {}) {
  try {
    return await postJson(path, json, { signal });
  } catch (err) {
    if (!isUseAJob(err)) throw err;
    return runJob(operation, json, { signal, onProgress });
  }
}

/** Title, detail and pointer lines of an error, for display. */
export function describe(err) {
  if (err instanceof ApiError) {
    const p = err.problem;
    const status = p.status ? `${p.status} ` : "";
    const errors = p.errors || [];
    const items = errors.slice(0, 4).map((e) => {
      const pointer = e.field ? (e.index ?? null) !== null ? `${e.field}[${e.index}]` : e.field
        : "";
      return pointer ? `${pointer}: ${e.reason}` : e.reason;
    }).filter((item, k) => {
      // No echo of the detail: the same text, its reason, or another wording about the
      // same field.
      const detail = p.detail || "", pointer = item.split(":")[0];
      return !detail.includes(item) && !(errors[k].reason && detail.includes(errors[k].reason))
        && !(errors[k].field && detail.startsWith(`${pointer}:`));
    });
    if (errors.length > 4) items.push(`… and ${errors.length - 4} more`);
    return { title: `${status}${p.title || "Error"}`, detail: p.detail || "", items,
      kind: p.kind || "", context: err.context };
  }
  return { title: err.name || "Error", detail: err.message || String(err), items: [],
    kind: "", context: "" };
}
