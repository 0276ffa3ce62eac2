// Viridis colour ramp (matplotlib's), per-vertex colour arrays and the legend gradient.

import { select } from "./mesh.js";

const VIRIDIS = [
  [68, 1, 84], [71, 45, 123], [59, 82, 139], [44, 114, 142], [33, 145, 140],
  [40, 174, 128], [94, 201, 98], [173, 220, 48], [253, 231, 37],
];

/** The k-th smallest |value| (0-based). */
function kthAbs(values, k) {
  const a = new Float64Array(values.length);
  for (let i = 0; i < a.length; i++) a[i] = Math.abs(values[i]);
  return select(a, k);
}

/** sRGB [0, 255] triple of viridis at t in [0, 1]. */
export function viridis(t) {
  const x = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(x)), f = x - i;
  const a = VIRIDIS[i], b = VIRIDIS[i + 1];
  return [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f];
}

export const CSS_GRADIENT = `linear-gradient(to right, ${VIRIDIS.map(
  (c, i) => `rgb(${c.join(",")}) ${((100 * i) / (VIRIDIS.length - 1)).toFixed(1)}%`).join(", ")})`;

function toLinear(c) {
  const s = c / 255;
  return s <= 0.04045 ? s / 12.92 : Math.pow((s + 0.055) / 1.055, 2.4);
}

// Linear RGB of the ramp at 1024 steps: a colour per vertex is a table look-up.
const STEPS = 1024;
const TABLE = new Float32Array(3 * (STEPS + 1));
for (let i = 0; i <= STEPS; i++) TABLE.set(viridis(i / STEPS).map(toLinear), 3 * i);

/**
 * Scale of a scalar field: linear over [0, max], or log10 over [min positive, max] for values
 * that span orders of magnitude (integrability defects).
 *   floor: the linear ramp never ends below it, so round-off (a shape back at rest, float32
 *          vertices) stays at the dark end instead of being stretched over the whole ramp;
 *          `quiet` says that every value is below it.
 *   min, max: fixed ends of a log ramp (exact forms: round-off up to the tolerance).
 */
export function scaleFor(values, { log = false, clip = 0.98, floor = 0, min, max: top } = {}) {
  let max = 0, minPositive = Infinity;
  for (const v of values) {
    const a = Math.abs(v);
    if (a > max) max = a;
    if (a > 0 && a < minPositive) minPositive = a;
  }
  if (!log) {
    // A few extreme values (a dragged spike) would leave the rest of the map one colour:
    // the ramp ends at the `clip` quantile and the legend says "≥".
    const n = values.length;
    const q = n ? kthAbs(values, Math.min(n - 1, Math.floor(clip * n))) : 0;
    if (max <= floor) return { log: false, min: 0, max: floor || 1, clipped: false, quiet: true };
    const end = Math.max(q, floor);
    return end > 0 && end < max ? { log: false, min: 0, max: end, clipped: true, quiet: false }
      : { log: false, min: 0, max, clipped: false, quiet: false };
  }
  if (min !== undefined && top !== undefined) return { log: true, min, max: top, clipped: max > top };
  if (!(max > 0)) return { log: true, min: 1e-17, max: 1e-16 };
  const lo = Math.max(minPositive, max * 1e-8, min ?? 0);
  return { log: true, min: lo, max: lo >= max ? lo * 10 : max };
}

export function normalized(value, scale) {
  const a = Math.abs(value);
  if (scale.log) {
    const lo = Math.log10(scale.min), hi = Math.log10(scale.max);
    return a <= 0 ? 0 : (Math.log10(a) - lo) / (hi - lo);
  }
  return a / scale.max;
}

/** Float32Array(3n) of linear RGB for three.js vertex colours. */
export function vertexColors(values, scale) {
  const out = new Float32Array(values.length * 3);
  for (let i = 0; i < values.length; i++) {
    const t = normalized(values[i], scale);
    const k = 3 * Math.round(STEPS * Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)));
    out[3 * i] = TABLE[k];
    out[3 * i + 1] = TABLE[k + 1];
    out[3 * i + 2] = TABLE[k + 2];
  }
  return out;
}

export function uniformColors(n, css = [200, 206, 214]) {
  const out = new Float32Array(n * 3);
  const rgb = css.map(toLinear);
  for (let i = 0; i < n; i++) out.set(rgb, 3 * i);
  return out;
}
