// The answers' warnings (report.warnings: {code, message, value, limit} of each documented
// threshold the answer is past, docs/service.md#warnings), shown the same way in every panel
// that shows an answer: a list under a "Check this answer" heading, hidden when there is none.

/** Show `warnings` (a report's list, or nothing) in the element `id` (a <div>). */
export function showAnswerWarnings(id, warnings) {
  const box = document.getElementById(id);
  const list = Array.isArray(warnings) ? warnings : [];
  box.hidden = list.length === 0;
  box.replaceChildren();
  if (!list.length) return;
  const title = document.createElement("strong");
  title.textContent = list.length === 1 ? "Check this answer:" : `Check this answer (${list.length} warnings):`;
  const items = document.createElement("ul");
  for (const warning of list) {
    const item = document.createElement("li");
    item.textContent = warning.message;
    item.dataset.code = warning.code;
    items.append(item);
  }
  box.append(title, items);
}
