// The page, wired: the state (store.js), the 3D and flat views (viewer.js), the panels (one
// per tab of index.html's tab list, the tabs' one declaration), mouse and keyboard
// (input.js), and the worker that reads meshes (worker-client.js). Everything the page knows
// comes from the service's public HTTP API. `?sample=<file>` picks the first mesh,
// `?transport=http|deform` pins the deformation path, and `?test` installs the browser
// tests' `window.app` (test-hooks.js).

import { installAnalysisPanel } from "./analysis-panel.js";
import { installBlendPanel } from "./blend-panel.js";
import { installColorView } from "./color-view.js";
import { installDeformPanel } from "./deform-panel.js";
import { installFlattenPanel } from "./flatten-panel.js";
import { installInput } from "./input.js";
import { installMeshPanel } from "./mesh-panel.js";
import { installProgress, track } from "./progress.js";
import { installRebuildPanel } from "./rebuild-panel.js";
import { store } from "./store.js";
import { showError, status } from "./toasts.js";
import { FlatView } from "./flat-view.js";
import { MeshView } from "./viewer.js";
import { WorkerClient } from "./worker-client.js";
import { apiKey, askForKey } from "./auth.js";
import { getJson } from "./api.js";

const $ = (id) => document.getElementById(id);
const query = new URLSearchParams(location.search);
const pinned = query.get("transport");

// Reading meshes and the big JSON of forms and reports happen in js/worker.js; every call
// settles (js/worker-client.js bounds the waits and says in words what did not answer).
const worker = new WorkerClient("/static/js/worker.js");
// The worker's requests carry the page's API key; a 401 asks for one and calls again.
const inWorker = async (kind, args, label) => {
  for (;;) {
    try {
      return await worker.call(kind, { ...args, apiKey: apiKey() }, label);
    } catch (err) {
      if (err?.status !== 401 || !await askForKey(err.problem)) throw err;
    }
  }
};

const page = {};  // the views and panels, once start() has made them

async function start() {
  const view = page.view = new MeshView($("view-3d"));
  const flatView = new FlatView($("view-flat"));
  installProgress();
  installColorView(view);
  const analyze = installAnalysisPanel({ inWorker });
  page.mesh = installMeshPanel({ view, inWorker, analyze });
  installRebuildPanel({ view, openMesh: page.mesh.openMesh, analyze });
  page.flatten = installFlattenPanel({ view, flatView });
  page.deform = installDeformPanel({ view, pinned });
  page.blend = installBlendPanel({ view });
  const { select, makeHandle, removeHandle, undo, redo } = page.deform;
  installInput({ view, actions: { select, makeHandle, removeHandle, undo, redo,
    setUp: page.mesh.setUp } });
  // a service with keys: the key is asked for here, before any upload
  const me = await getJson("/v1/me");
  store.set({ sizeLimits: me.size_limits ?? null });
  const samples = await page.mesh.loadSampleList();
  const first = query.get("sample") ?? samples[0]?.file;
  if (first) await page.mesh.loadSample(first);
  else status("Ready: pick a sample or upload a mesh.");
}

let startup = "starting";
const ready = track(start()).then(() => { startup = "ready"; },
  (err) => { startup = "failed"; showError(err); });

if (query.has("test")) {
  import("./test-hooks.js").then(({ installTestHooks }) => installTestHooks({ page, worker,
    ready, startup: () => startup, pinned }));
}
