// The API key of a service with keys (docs/deployment.md, "API keys"): asked for when the
// service answers 401, kept for this tab only (sessionStorage, never localStorage or a
// cookie), sent as `Authorization: Bearer <key>` and, for a session's WebSocket, as the
// subprotocol `bearer.<key>` next to `ffs` (browsers cannot set headers on a WebSocket; the
// key never goes into a URL). The module worker has no sessionStorage: the page hands it the
// key with each call (setApiKey).

const STORAGE = "ffs.apiKey";
let workerKey = null;
let asking = null;  // one prompt for every request that met a 401 at once

const inPage = () => typeof document !== "undefined" && typeof sessionStorage !== "undefined";

/** The key in use, or null. */
export function apiKey() {
  if (!inPage()) return workerKey;
  try {
    return sessionStorage.getItem(STORAGE);
  } catch {
    return null;
  }
}

/** The worker's copy of the page's key (null: none). */
export function setApiKey(key) {
  workerKey = key || null;
}

/** Forget the key (a 401 with it: it is not known). */
export function forgetApiKey() {
  if (inPage()) sessionStorage.removeItem(STORAGE);
  workerKey = null;
}

/** The Authorization header of the key, or nothing. */
export function authHeaders() {
  const key = apiKey();
  return key ? { Authorization: `Bearer ${key}` } : {};
}

/** The subprotocols of a session's WebSocket: ["ffs", "bearer.<key>"], or none. */
export function socketProtocols() {
  const key = apiKey();
  return key ? ["ffs", `bearer.${key}`] : undefined;
}

/** Whether this context can ask the user (the page; not the worker). */
export function canAsk() {
  return inPage();
}

/**
 * Ask for a key (a modal dialog); resolves with it (stored for the tab) or null when the
 * user cancels. `problem` is the 401's problem document: its detail is shown.
 */
export function askForKey(problem) {
  if (!inPage()) return Promise.resolve(null);
  asking ??= showDialog(problem).finally(() => { asking = null; });
  return asking;
}

/** A new element with these properties. */
function element(tag, properties) {
  return Object.assign(document.createElement(tag), properties);
}

function showDialog(problem) {
  const hadKey = Boolean(apiKey());
  forgetApiKey();
  const dialog = element("dialog", { id: "api-key-dialog", className: "api-key-dialog" });
  const title = element("h2", { textContent: "API key required" });
  const text = element("p", { textContent: hadKey
    ? "The service does not know this key. Enter another one."
    : "This service needs an API key. Ask whoever runs it for one.",
  title: problem?.detail || "" });  // the service's own words, on hover
  const note = element("p", { className: "api-key-note",
    textContent: "The key is kept for this tab only and sent to this service alone." });
  const form = element("form", { method: "dialog" });
  const input = element("input", { type: "password", name: "key", autocomplete: "off",
    required: true, id: "api-key-input", placeholder: "API key" });
  input.setAttribute("aria-label", "API key");
  const use = element("button", { type: "submit", value: "use", textContent: "Use key",
    id: "api-key-use" });
  const cancel = element("button", { type: "button", textContent: "Cancel",
    id: "api-key-cancel" });
  form.append(input, use, cancel);
  dialog.append(title, text, form, note);
  document.body.append(dialog);
  return new Promise((resolve) => {
    const finish = (key) => {
      dialog.close();
      dialog.remove();
      if (key) sessionStorage.setItem(STORAGE, key);
      resolve(key || null);
    };
    form.addEventListener("submit", (event) => {
      event.preventDefault();
      finish(input.value.trim());
    });
    cancel.addEventListener("click", () => finish(null));
    dialog.addEventListener("cancel", (event) => {
      event.preventDefault();
      finish(null);
    });
    dialog.showModal();
    input.focus();
  });
}
