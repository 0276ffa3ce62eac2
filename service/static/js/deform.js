// Live deformation transports. Each one takes the same set-up (rest mesh, handle vertices,
// rotation groups, options) and answers solve(handlePositions, handleRotations) with the new
// vertices (Float64Array(3n)):
//   SessionTransport  POST /v1/sessions once (the factorization), then per update the session
//                     WebSocket (links.ws of the session), or POST /v1/sessions/{id}/solve
//                     with a float32 answer when there is no socket;
//   DeformTransport   POST /v1/deform per update (servers without sessions), the mesh
//                     in a binary body (application/vnd.ffs.arrays).
// Wire formats (docs/service.md): a drag is JSON {handle_positions, handle_rotations?, seq?};
// vertices come back as little-endian float32 (n, 3); a WebSocket reply puts an 8-byte header
// in front (uint32 seq, uint32 n) and a text frame is a problem document (with "seq").
// The page keeps one drag in flight, so the server's "newest drag wins" never drops one.
// Progressive sessions (setup.refine: options.refine true): solve() resolves with the linear
// shape at once; the refined shape of the newest drag comes later through onRefined(vertices,
// report): over the socket a second reply whose JSON trailer (after the 12 n bytes) says
// {"shape": "refined", ...}, over HTTP the drag's Link rel="refined", long-polled.

import { ApiError, isUseAJob, postArrays, request, runJob } from "./api.js";
import { socketProtocols } from "./auth.js";
import { flatten3, rows3 } from "./mesh.js";

/** The small fields of a deformation body (handles, rotations, options) for a set-up and
 * handle targets: everything but the mesh. */
export function deformParams(setup, positions, rotations) {
  const params = {
    handles: setup.handles.map((vertex, k) => ({ vertex,
      position: [positions[3 * k], positions[3 * k + 1], positions[3 * k + 2]] })),
    options: { orthonormalize: setup.orthonormalize,
      ...(setup.refine === undefined ? {} : { refine: setup.refine }) },
  };
  if (setup.rotationGroups.length) {
    params.rotations = setup.rotationGroups.map((faces, k) => ({ faces, rotation: rotations[k] }));
  }
  return params;
}

/** JSON body of POST /v1/sessions (and of POST /v1/deform) for a set-up and handle targets. */
export function deformBody(setup, positions, rotations) {
  return { vertices: rows3(setup.rest), faces: rows3(setup.faces),
    ...deformParams(setup, positions, rotations) };
}

/** Little-endian float32 (n, 3) from byte `offset` -> Float64Array(3n). With `trailer`, the
 * 12 n bytes may be followed by more (a progressive session's JSON trailer). */
export function decodeVertices(buffer, n, offset = 0, { trailer = false } = {}) {
  const view = new DataView(buffer, offset, n === undefined ? undefined
    : Math.min(12 * n, buffer.byteLength - offset));
  const size = buffer.byteLength - offset;
  if (n !== undefined && (trailer ? size < 12 * n : size !== 12 * n)) {
    throw new Error(`expected ${12 * n} bytes of vertices, got ${size}`);
  }
  const out = new Float64Array(view.byteLength / 4);
  for (let i = 0; i < out.length; i++) out[i] = view.getFloat32(4 * i, true);
  return out;
}

const WS_HEADER_BYTES = 8;

/** The JSON trailer of a WebSocket reply with n vertices (null when there is none). */
function replyTrailer(buffer, n) {
  const start = WS_HEADER_BYTES + 12 * n;
  if (buffer.byteLength <= start) return null;
  return JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, start)));
}

export class DeformTransport {
  constructor(setup) {
    this.setup = setup;
    this.kind = "deform";
    this.label = "HTTP: POST /v1/deform per update (this server has no sessions)";
  }

  async open() {}

  async solve(positions, rotations) {
    // The mesh as a binary body (application/vnd.ffs.arrays): it goes with every update.
    const { rest, faces } = this.setup;
    let result;
    try {
      result = await postArrays("/v1/deform", deformParams(this.setup, positions, rotations),
        { vertices: [rest, [rest.length / 3, 3]], faces: [faces, [faces.length / 3, 3]] });
    } catch (err) {
      if (!isUseAJob(err)) throw err;
      // Too large for a synchronous answer (413 use-a-job): the same deformation as a job.
      result = await runJob("deform", deformBody(this.setup, positions, rotations));
    }
    return flatten3(result.vertices);
  }

  close() {}
}

/** How long the page waits for a drag's refined shape before it stops counting it as work
 * in progress (the shape is still applied if it comes later). */
const REFINED_WAIT_MS = 120000;

export class SessionTransport {
  /** `onRefined(vertices, report)`: a progressive session's refined shape of the newest drag. */
  constructor(setup, { websocket = true, onRefined = null } = {}) {
    this.setup = setup;
    this.kind = "session";
    this.onRefined = onRefined;
    this.drags = 0;  // drags sent (the newest one's refined shape is the one that counts)
    this.refinedShapes = 0;
    this.waiting = null;  // { drag, resolve }: the newest drag's refined shape, not yet here
    this.useWebSocket = websocket;
    this.socket = null;
    this.id = null;
    this.label = "HTTP: POST /v1/sessions/{id}/solve";
  }

  async open() {
    const body = deformBody(this.setup, this.setup.initialPositions, this.setup.initialRotations);
    const response = await request("/v1/sessions", { json: body });
    const session = await response.json();
    this.id = session.id;
    this.session = session;
    this.n = session.n_vertices ?? this.setup.rest.length / 3;
    this.label = `HTTP: POST /v1/sessions/${this.id.slice(0, 8)}…/solve`;
    this.seq = 0;
    const ws = session.links?.ws;
    if (this.useWebSocket && ws) await this.openSocket(ws);
  }

  async openSocket(path) {
    // Opened only when the session advertises it (links.ws); a socket that fails to open
    // or closes leaves the HTTP solve endpoint in charge.
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    const url = new URL(path, `${scheme}//${location.host}`).href;
    await new Promise((resolve) => {
      let socket;
      try {
        socket = new WebSocket(url, socketProtocols());  // the key, not in the URL
      } catch (err) {
        console.warn("WebSocket unavailable, using HTTP", err);
        resolve();
        return;
      }
      socket.binaryType = "arraybuffer";
      const timer = setTimeout(() => {
        socket.close();
        resolve();
      }, 3000);
      socket.onopen = () => {
        clearTimeout(timer);
        this.socket = socket;
        this.label = `WebSocket: /v1/sessions/${this.id.slice(0, 8)}…/ws`;
        resolve();
      };
      socket.onerror = () => {
        clearTimeout(timer);
        resolve();
      };
      socket.onclose = (event) => {
        if (this.socket === socket) {
          this.socket = null;
          this.settle();
          this.label = `HTTP: POST /v1/sessions/${this.id?.slice(0, 8)}…/solve (socket closed)`;
          const reject = this.reject;
          this.resolve = this.reject = null;
          reject?.(Object.assign(new Error(`the session WebSocket closed (${event.code}`
            + `${event.reason ? ` ${event.reason}` : ""})`), { name: "SocketClosed" }));
        }
      };
      socket.onmessage = (event) => this.onMessage(event);
    });
  }

  onMessage(event) {
    let seq, result, error;
    if (typeof event.data === "string") {
      // A text frame is a problem document about drag `seq`.
      let doc;
      try {
        doc = JSON.parse(event.data);
      } catch {
        doc = { title: "Unexpected WebSocket message", detail: event.data.slice(0, 200) };
      }
      seq = doc.seq;
      error = new ApiError(doc, `WebSocket ${new URL(this.socket?.url ?? location.href).pathname}`);
    } else {
      const header = new DataView(event.data, 0, WS_HEADER_BYTES);
      seq = header.getUint32(0, true);
      const n = header.getUint32(4, true);
      try {
        result = decodeVertices(event.data, n, WS_HEADER_BYTES, { trailer: true });
        const trailer = replyTrailer(event.data, n);
        if (trailer?.shape === "refined") {
          // The refined shape follows the drag's linear one: only the newest drag's counts.
          if (seq === this.seq) this.refined(result, trailer);
          return;
        }
      } catch (err) {
        error = err;
      }
    }
    if (!this.resolve || (seq !== undefined && seq !== null && seq !== this.pendingSeq)) return;
    const resolve = this.resolve, reject = this.reject;
    this.resolve = this.reject = null;
    if (error) reject(error);
    else resolve(result);
  }

  solveBody(positions, rotations) {
    const body = { handle_positions: rows3(positions) };
    if (this.setup.rotationGroups.length) body.handle_rotations = rotations;
    return body;
  }

  solve(positions, rotations) {
    const pending = this.solveOnce(positions, rotations);
    this.inflight = pending.catch(() => {}).finally(() => {
      if (this.inflight === guard) this.inflight = null;
    });
    const guard = this.inflight;
    return pending;
  }

  refined(vertices, report) {
    this.refinedShapes++;
    this.lastRefinement = report;
    this.onRefined?.(vertices, report);
    this.refinedDrag = this.drags;
    this.settle();
  }

  /** A promise that settles once the newest drag's refined shape has been applied, a newer
   * drag superseded it, the session closed, or REFINED_WAIT_MS passed (then the page keeps
   * the linear shape); at once for a session that does not refine. The page counts it as
   * work in progress, so that what it shows next (a download, a test) is the settled shape. */
  settled() {
    if (!this.setup.refine || !this.id || this.refinedDrag === this.drags
        || this.unrefinedDrag === this.drags) return Promise.resolve();
    if (!this.waiting || this.waiting.drag !== this.drags) {
      this.settle();
      let resolve;
      const promise = new Promise((r) => { resolve = r; });
      const timer = setTimeout(() => this.settle(), REFINED_WAIT_MS);
      this.waiting = { drag: this.drags, promise, resolve: () => { clearTimeout(timer); resolve(); } };
    }
    return this.waiting.promise;
  }

  settle() {
    const waiting = this.waiting;
    this.waiting = null;
    waiting?.resolve();
  }

  /** Long-poll a drag's refined shape (HTTP; `link` from its Link header) until it is ready,
   * superseded (409: a newer drag) or no longer wanted (a newer drag was sent). */
  async followRefined(link, drag) {
    while (this.id && drag === this.drags) {
      let response;
      try {
        response = await request(`${link}?wait=20`, { method: "GET",
          accept: "application/octet-stream", timeoutMs: 30000 });
      } catch (err) {
        if (err instanceof ApiError && err.status !== 409 && err.status !== 0) {
          console.warn("[ffs] refined shape unavailable", err);
        }
        if (drag === this.drags) this.settle();
        return;
      }
      if (response.status === 202) continue;
      const vertices = decodeVertices(await response.arrayBuffer(), this.n);
      if (drag !== this.drags) return;  // a newer drag was sent meanwhile
      let report = null;
      try {
        report = JSON.parse(response.headers.get("X-Refinement") ?? "null");
      } catch { /* the shape is what matters */ }
      this.refined(vertices, report);
      return;
    }
  }

  async solveOnce(positions, rotations) {
    const body = this.solveBody(positions, rotations);
    const drag = ++this.drags;
    if (this.socket && this.socket.readyState === WebSocket.OPEN) {
      this.seq = (this.seq + 1) % 2 ** 32;
      this.pendingSeq = this.seq;
      return new Promise((resolve, reject) => {
        this.resolve = resolve;
        this.reject = reject;
        this.socket.send(JSON.stringify({ ...body, seq: this.seq }));
      });
    }
    const response = await request(`/v1/sessions/${this.id}/solve`, { json: body,
      accept: "application/octet-stream" });
    const vertices = decodeVertices(await response.arrayBuffer(), this.n);
    const link = /<([^>]+)>;\s*rel="refined"/.exec(response.headers.get("Link") ?? "");
    if (link) this.followRefined(link[1], drag);
    else this.unrefinedDrag = drag;  // nothing more will come for it
    return vertices;
  }

  /** Close the socket and delete the session once the solve in flight (if any) is done;
   * `unloading`: right now, with a request that outlives the page. */
  close({ unloading = false } = {}) {
    const socket = this.socket, id = this.id;
    this.id = null;
    this.settle();
    const finish = () => {
      if (socket) {
        if (this.socket === socket) this.socket = null;
        socket.close(1000, "done");
      }
      if (id) {
        request(`/v1/sessions/${id}`, { method: "DELETE", keepalive: unloading })
          .catch((err) => console.warn(`could not delete session ${id}`, err));
      }
    };
    if (this.inflight && !unloading) this.inflight.then(finish);
    else finish();
  }
}
