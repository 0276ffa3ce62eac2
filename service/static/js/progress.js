// The progress bar (one at a time: a label, a fraction or an indeterminate stripe, and a
// Cancel button for cancellable work) and the page's count of work in progress, which
// `idle()` waits out (the browser tests wait on it).

import { showError } from "./toasts.js";

const $ = (id) => document.getElementById(id);

let busy = 0;
const idleWaiters = [];

/** Count `promise` as work in progress until it settles; returns it. */
export function track(promise) {
  busy++;
  return promise.finally(() => {
    busy--;
    if (!busy) idleWaiters.splice(0).forEach((resolve) => resolve());
  });
}

/** A promise that resolves when no tracked work is left. */
export function idle() {
  return busy ? new Promise((resolve) => idleWaiters.push(resolve)) : Promise.resolve();
}

export const busyCount = () => busy;

/** Run an async UI action: tracked for idle(), errors shown, never thrown away. */
export function action(fn) {
  return (...args) => track(Promise.resolve().then(() => fn(...args))).catch(showError);
}

/** On each `change` of the file input `input`, the chosen file goes to `action(fn)`; the
 * input is cleared first, so that choosing the same file again is a change too. */
export function onFileChosen(input, fn) {
  input.addEventListener("change", (event) => {
    const file = event.target.files[0];
    event.target.value = "";
    if (file) action(fn)(file);
  });
}

let controller = null;

function start(label, { cancellable = false } = {}) {
  $("progress").hidden = false;
  $("progress").classList.add("indeterminate");
  $("progress-bar").style.width = "";
  $("progress-label").textContent = label;
  controller = cancellable ? new AbortController() : null;
  $("progress-cancel").hidden = !cancellable;
  return controller?.signal;
}

function update(fraction, label) {
  $("progress").classList.remove("indeterminate");
  $("progress-bar").style.width = `${Math.round(100 * fraction)}%`;
  $("progress-label").textContent = label;
}

/** Run `fn(signal)` under the progress bar; `signal` aborts when the user cancels
 * (`{cancellable: true}`). */
export async function withProgress(label, fn, options) {
  const signal = start(label, options);
  try {
    return await fn(signal);
  } finally {
    $("progress").hidden = true;
    controller = null;
  }
}

/** An api.runJob() onProgress callback that shows the job's status and stage. */
export function jobProgress(label) {
  return (job) => {
    const p = job.progress || {};
    const stage = p.stage ? ` · ${p.stage}` : "";
    update(p.fraction ?? 0, `${label}: ${job.status}${stage} · ${Math.round(100 * (p.fraction ?? 0))} %`);
  };
}

/** What the progress bar says, or null when it is hidden. */
export const progressLabel = () => ($("progress").hidden ? null : $("progress-label").textContent);

export function installProgress() {
  $("progress-cancel").addEventListener("click", () => controller?.abort());
}
