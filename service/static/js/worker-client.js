// The page's side of js/worker.js: calls as promises that always settle.
//
// The worker says {ready: true} once its message handler is installed, and the page posts
// nothing before that (a message that reaches a worker with no handler yet is dropped, and
// its reply would never come). The worker acknowledges each call ({id, accepted: true}) and
// says {alive: true} every few seconds while it works. A call is rejected, in words, when the
// worker does not start, does not take the call up, goes silent, fails, or does not answer
// within the reply bound; the worker is then ended and a new one starts with the next call.

import { ApiError } from "./api.js";

/** Bounds in milliseconds (the worker pulses every 5 s while it works). */
export const WORKER_LIMITS = { startMs: 30_000, ackMs: 15_000, silenceMs: 30_000,
  replyMs: 300_000 };

const seconds = (ms) => `${Math.round(ms / 100) / 10} s`;

export class WorkerClient {
  /** `limits` (a WORKER_LIMITS-like object) is read at every check: tests may change it. */
  constructor(url, limits = { ...WORKER_LIMITS }) {
    this.url = url;
    this.limits = limits;
    this.calls = new Map();  // id -> {kind, label, since, posted, accepted, resolve, reject}
    this.nextId = 0;
    this.worker = null;
    this.started = null;     // promise: the current worker listens
    this.startedAt = 0;
    this.listening = false;
    this.heardAt = 0;
    this.watchdog = null;
  }

  /** Run `kind` with `args` in the worker; `label` says what it is doing, in words. */
  call(kind, args, label = kind) {
    const id = ++this.nextId;
    const call = { kind, label, since: performance.now(), posted: null, accepted: false };
    const promise = new Promise((resolve, reject) => Object.assign(call, { resolve, reject }));
    this.calls.set(id, call);
    this.watch();
    const worker = this.start();
    this.started.then(() => {
      if (!this.calls.has(id) || this.worker !== worker) return;  // failed meanwhile
      call.posted = performance.now();
      worker.postMessage({ id, kind, args });
    }, () => {});  // a failed start rejects the call through fail()
    return promise;
  }

  /** The calls waiting for an answer, for diagnostics. */
  pending() {
    const now = performance.now();
    return [...this.calls.values()].map((c) => ({ kind: c.kind, label: c.label,
      waitingMs: Math.round(now - c.since), posted: c.posted !== null, accepted: c.accepted }));
  }

  start() {
    if (this.worker) return this.worker;
    const worker = new Worker(this.url, { type: "module" });
    this.worker = worker;
    this.listening = false;
    this.startedAt = this.heardAt = performance.now();
    this.started = new Promise((resolve, reject) => {
      this.startWaiter = { resolve, reject };
    });
    this.started.catch(() => {});
    worker.onmessage = ({ data }) => this.receive(worker, data);
    worker.onerror = (event) => {
      event.preventDefault();
      this.fail(worker, `The page's background worker failed (${event.message
        || "it could not start"}).`);
    };
    worker.onmessageerror = () => this.fail(worker,
      "An answer of the page's background worker could not be read.");
    return worker;
  }

  receive(worker, data) {
    if (worker !== this.worker) return;
    this.heardAt = performance.now();
    if (data.ready) {
      this.listening = true;
      this.startWaiter.resolve();
      return;
    }
    if (data.alive) return;
    const call = this.calls.get(data.id);
    if (!call) return;
    if (data.accepted) {
      call.accepted = true;
      return;
    }
    this.calls.delete(data.id);
    this.watch();
    const { result, error } = data;
    if (!error) call.resolve(result);
    else if (error.problem) call.reject(new ApiError(error.problem, error.context));
    else call.reject(Object.assign(new Error(error.message), { name: error.name }));
  }

  /** End `worker` and reject every call with `detail`; the next call starts a new worker. */
  fail(worker, detail) {
    if (worker !== this.worker) return;
    worker.terminate();
    this.worker = null;
    const err = new ApiError({ title: "The page stopped waiting", status: 0,
      detail: `${detail} It was restarted: try again.` }, "the page's background worker");
    this.startWaiter.reject(err);
    const calls = [...this.calls.values()];
    this.calls.clear();
    this.watch();
    for (const call of calls) call.reject(err);
  }

  /** A check every half second while there are calls. */
  watch() {
    if (this.calls.size && !this.watchdog) this.watchdog = setInterval(() => this.check(), 500);
    if (!this.calls.size && this.watchdog) {
      clearInterval(this.watchdog);
      this.watchdog = null;
    }
  }

  check() {
    const worker = this.worker, now = performance.now(), limits = this.limits;
    if (!worker) return;
    if (!this.listening && now - this.startedAt > limits.startMs) {
      this.fail(worker, `The page's background worker did not start within ${seconds(limits.startMs)}.`);
      return;
    }
    for (const call of this.calls.values()) {
      if (call.posted !== null && !call.accepted && now - call.posted > limits.ackMs) {
        this.fail(worker, `The page's background worker did not begin ${call.label} within `
          + `${seconds(limits.ackMs)}.`);
        return;
      }
      if (call.accepted && now - this.heardAt > limits.silenceMs) {
        this.fail(worker, `The page's background worker stopped responding (nothing for `
          + `${seconds(limits.silenceMs)}) while ${call.label}.`);
        return;
      }
      if (now - call.since > limits.replyMs) {
        this.fail(worker, `No answer after ${seconds(limits.replyMs)} while ${call.label}.`);
        return;
      }
    }
  }
}
