// Numbers and reports in words for the panels: short numbers, percentages and degrees, the
// definition lists (<dl>) of the panels' statistics, and the global loops of a report.

export function fmt(x, digits = 3) {
  if (x === null || x === undefined || Number.isNaN(x)) return "–";
  const a = Math.abs(x);
  if (a === 0) return "0";
  if (a < 1e-3 || a >= 1e5) return x.toExponential(digits - 1);
  return Number(x.toPrecision(digits)).toString();
}

export const pct = (x) => `${(100 * x).toFixed(x < 0.001 ? 3 : 2)} %`;
export const deg = (x) => `${((180 / Math.PI) * x).toFixed(2)}°`;
export const DEFECT_LABELS = { vertex_defect: "Total", gauss_defect: "Gauss",
  codazzi_defect: "Codazzi" };
export const maxOf = (values) => values.reduce((a, b) => Math.max(a, Math.abs(b)), 0);

/** Fill the <dl> `id` with [label, value (text or a node), class of the value] rows. */
export function setStats(id, rows) {
  const dl = document.getElementById(id);
  dl.replaceChildren();
  for (const [label, value, cls] of rows) {
    const dt = document.createElement("dt"), dd = document.createElement("dd");
    dt.textContent = label;
    if (value instanceof Node) dd.append(value);
    else dd.textContent = value;
    if (cls) dd.className = cls;
    dl.append(dt, dd);
  }
}

/** A number (or short value) that never breaks across lines. */
export function num(text) {
  const span = document.createElement("span");
  span.className = "num";
  span.textContent = text;
  return span;
}

export function badge(ok, yes = "yes", no = "no") {
  const span = document.createElement("span");
  span.className = `badge ${ok ? "ok" : "bad"}`;
  span.textContent = ok ? yes : no;
  return span;
}

/** The global loops of a report in words: how many pass, and the worst of each kind with
 * its unit (a rotation in radians, a translation in mean edge lengths: report.max_defect
 * mixes the two with the vertex defects, so the page never shows it bare). */
export function loopsText(r) {
  const { rotation, translation } = r.global_holonomy;
  const loops = [...rotation, ...translation];
  if (!loops.length) return "none";
  const worst = (list) => list.reduce((a, l) => Math.max(a, l.magnitude), 0);
  const failing = [];
  if (worst(rotation) > r.tolerance) failing.push(`rotation ${fmt(worst(rotation), 3)} rad`);
  if (worst(translation) > r.tolerance) {
    failing.push(`translation ${fmt(worst(translation), 3)} mean edge lengths`);
  }
  return `${loops.filter((l) => l.passes).length} / ${loops.length} pass`
    + (failing.length ? ` (worst: ${failing.join(", ")})` : "");
}
