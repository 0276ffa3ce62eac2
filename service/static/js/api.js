// The service's public HTTP API as used by the page. Every failure becomes an ApiError that
// carries the RFC 9457 problem document (or one made up for network errors), so the page can
// show a readable message; nothing is swallowed here.

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

/** fetch() with problem-document errors. `json` or `form` is the body. */
export async function request(path, { method = "POST", json, form, body, contentType,
  accept = "application/json", signal, keepalive = false } = {}) {
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
  let response;
  try {
    response = await fetch(path, { method, headers, body, signal, keepalive });
  } catch (err) {
    if (err.name === "AbortError") throw err;
    throw new ApiError({ title: "Network error", status: 0,
      detail: `${context} failed: ${err.message}. Is the service running?` }, context);
  }
  if (!response.ok) throw await problemFrom(response, context);
  return response;
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

export async function meshGlb(vertices, faces) {
  const response = await request("/v1/mesh", { json: { vertices, faces },
    accept: "model/gltf-binary" });
  return response.blob();
}

/** Which optional parts of the API this server has (from its OpenAPI document). */
export async function capabilities() {
  const doc = await getJson("/openapi.json");
  const paths = doc.paths || {};
  const reconstructOptions = doc.components?.schemas?.ReconstructOptions?.properties || {};
  return {
    sessions: "/v1/sessions" in paths,
    refine: "refine" in reconstructOptions,
    deformRefine: "refine" in (doc.components?.schemas?.DeformOptions?.properties || {}),
    sessionSolve: Object.keys(paths).some((p) => /^\/v1\/sessions\/\{[^}]+\}\/solve$/.test(p)),
    version: doc.info?.version,
  };
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
      // No echo of the detail: the same text, or another wording about the same field.
      const detail = p.detail || "", pointer = item.split(":")[0];
      return !detail.includes(item) && !(errors[k].field && detail.startsWith(`${pointer}:`));
    });
    if (errors.length > 4) items.push(`… and ${errors.length - 4} more`);
    return { title: `${status}${p.title || "Error"}`, detail: p.detail || "", items,
      kind: p.kind || "", context: err.context };
  }
  return { title: err.name || "Error", detail: err.message || String(err), items: [],
    kind: "", context: "" };
}
