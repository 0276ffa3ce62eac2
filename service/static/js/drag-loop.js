// The live deformation: which transport the drags run on (a session, over its WebSocket or
// HTTP, or POST /v1/deform per update when there is no session), reopened when the rest
// shape, the handle set or the options change, and the solve loop that keeps one drag in
// flight and sends the newest handle targets when the previous answer is in. No DOM: what
// the answers do to the page is the callbacks'.

import { ApiError, describe } from "./api.js";
import { DeformTransport, SessionTransport } from "./deform.js";
import { state, store } from "./store.js";

/** Session statuses that mean "no session for you now": deform per update instead. */
const SESSION_UNAVAILABLE = [404, 405, 429, 501, 503];

/** What a transport is opened for: the rest shape, the handle set and the options. */
function transportKey() {
  return { rest: state.rest, handles: state.handles.map((h) => h.id).join(","),
    orthonormalize: state.orthonormalize, refine: state.refineDrags };
}

export class DragLoop {
  /**
   * `setup()`: the deformation set-up of the current handles (deform.js); `targets()`:
   * {positions, rotations} of the handles now; `onShape(vertices)`: an answer to apply;
   * `onSolved()`: the newest answer is in; `preparing(fn)`: run the opening (e.g. under a
   * progress bar); `track(promise)`: count work in progress; `onError(err)`: show an error;
   * `pinned`: "http" (a session without WebSocket) or "deform" (no session), else null.
   */
  constructor({ setup, targets, onShape, onSolved, preparing, track, onError, pinned = null }) {
    Object.assign(this, { setup, targets, onShape, onSolved, preparing, track, onError, pinned });
    this.generation = 0;
    this.solving = null;  // the running solve loop (a promise), or null
    this.wanted = false;  // the handles moved since the last drag was sent
  }

  /** Close the open transport; a transport still opening is dropped when it opens. */
  close(options) {
    this.generation++;
    if (state.transport) state.transport.close(options);
    // The time per update was the closed transport's: the next one reports its own.
    store.set({ transport: null, transportKey: null, lastSolveMs: null });
  }

  /** Whether the open transport was opened for the current rest shape, handles and options. */
  current() {
    const key = state.transportKey, now = transportKey();
    return !!state.transport && !!key && key.rest === now.rest && key.handles === now.handles
      && key.orthonormalize === now.orthonormalize && key.refine === now.refine;
  }

  /** Open a transport for the current handles (closing the one open); `solve`: send the
   * handles' targets once it is open. */
  async open({ solve = true } = {}) {
    this.close();
    const generation = this.generation;
    if (!state.handles.length) return;
    const setup = this.setup();
    // ?transport=http (session, no WebSocket) or ?transport=deform (no session) pin a path.
    let transport = this.pinned !== "deform"
      ? new SessionTransport(setup, { websocket: this.pinned !== "http",
        onRefined: (vertices) => { if (transport === state.transport) this.onShape(vertices); } })
      : new DeformTransport(setup);
    await this.preparing(async () => {
      try {
        await transport.open();
      } catch (err) {
        if (!(transport instanceof SessionTransport && err instanceof ApiError
          && SESSION_UNAVAILABLE.includes(err.status))) throw err;
        console.warn("[ffs] sessions unavailable, deforming per request", describe(err));
        transport = new DeformTransport(setup);
        transport.label = "HTTP: POST /v1/deform per update";
      }
    });
    if (generation !== this.generation) {  // superseded while it opened
      transport.close();
      return;
    }
    store.set({ transport, transportKey: transportKey() });
    if (solve) this.request();
  }

  /** The handles moved: solve for their targets (now, or when the drag in flight is in). */
  request() {
    this.wanted = true;
    if (!this.solving) this.solving = this.track(this.loop());
  }

  async loop() {
    try {
      while (this.wanted && state.transport) {
        this.wanted = false;
        const transport = state.transport;
        const { positions, rotations } = this.targets();
        const t0 = performance.now();
        let vertices;
        try {
          vertices = await transport.solve(positions, rotations);
          if (transport.settled) this.track(transport.settled());  // the refined shape to come
        } catch (err) {
          if (transport !== state.transport) continue;  // replaced meanwhile: stale
          if (transport.kind === "session" && (err.status === 410 || err.status === 404)
            && !transport.replaced) {
            // The session expired (FFS_SESSION_TTL) or its worker went away: open a new one
            // for the same handles and carry on.
            console.warn("[ffs] session gone, opening a new one", describe(err));
            transport.replaced = true;
            transport.id = null;  // nothing left to delete
            await this.open();
            this.wanted = true;
            continue;
          }
          throw err;
        }
        if (transport !== state.transport) continue;
        store.set({ lastSolveMs: performance.now() - t0, solves: state.solves + 1 });
        this.onShape(vertices);
        if (!this.wanted) this.onSolved();
      }
    } catch (err) {
      this.onError(err);
    } finally {
      this.solving = null;
    }
  }
}
