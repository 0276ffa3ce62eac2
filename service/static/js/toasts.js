// What the page tells the user: the status line, and errors as toasts with the problem
// document's text (they close by themselves, not while hovered, and the same message again
// counts up instead of stacking a copy). Every error shown is kept in state.errors.

import { describe } from "./api.js";
import { state } from "./store.js";

/** How long a toast stays, in milliseconds (the browser tests shorten it). */
export const toastTiming = { ms: 8000 };
const MAX_TOASTS = 4;
const toastTimers = new WeakMap();

export function status(text) {
  document.getElementById("statusbar").textContent = text;
}

function closeToast(toast) {
  toast.classList.add("fading");
  setTimeout(() => toast.remove(), 300);
}

function scheduleClose(toast) {
  clearTimeout(toastTimers.get(toast));
  toastTimers.set(toast, setTimeout(() => closeToast(toast), toastTiming.ms));
}

function element(tag, className, text) {
  const node = document.createElement(tag);
  if (className) node.className = className;
  if (text !== undefined) node.textContent = text;
  return node;
}

function newToast(info, key) {
  const toast = element("div", "toast");
  toast.dataset.key = key;
  toast.dataset.count = "1";
  toast.setAttribute("role", "alert");
  const title = element("div", "toast-title", info.title);
  title.append(element("span", "toast-count"));
  toast.append(title, element("div", "toast-detail", info.detail));
  if (info.items.length) {
    const list = element("ul");
    for (const item of info.items) list.append(element("li", "", item));
    toast.append(list);
  }
  if (info.context) {  // which request failed: for developers, folded away
    const more = element("details");
    more.append(element("summary", "", "Technical details"), element("div", "toast-context",
      info.context + (info.kind ? ` · ${info.kind}` : "")));
    toast.append(more);
  }
  const close = element("button", "toast-close", "×");
  close.type = "button";
  close.setAttribute("aria-label", "Dismiss");
  close.addEventListener("click", () => toast.remove());
  toast.append(close);
  toast.addEventListener("mouseenter", () => clearTimeout(toastTimers.get(toast)));
  toast.addEventListener("mouseleave", () => scheduleClose(toast));
  return toast;
}

/** Show an error (an ApiError's problem document, or any Error) as a toast; a cancelled
 * action (AbortError) only says so in the status line. */
export function showError(err) {
  if (err?.name === "AbortError") {
    status("Cancelled.");
    return;
  }
  const info = describe(err);
  state.errors.push(info);
  console.warn("[ffs]", info.title, info.detail, err);
  const box = document.getElementById("toasts");
  const key = `${info.title}\n${info.detail}`;
  const same = [...box.children].find((t) => t.dataset.key === key && !t.classList.contains("fading"));
  if (same) {  // the same message again: count it instead of stacking a copy
    const n = Number(same.dataset.count) + 1;
    same.dataset.count = String(n);
    same.querySelector(".toast-count").textContent = `×${n}`;
    box.prepend(same);
    scheduleClose(same);
    return;
  }
  const toast = newToast(info, key);
  box.prepend(toast);
  scheduleClose(toast);
  while (box.children.length > MAX_TOASTS) box.lastChild.remove();
}
