// The 3D view's colours and their legend: plain, the integrability defect per vertex, the
// distortion of a deformed shape against the loaded one, or the checkerboard of the flat
// layout. Drawn from the state; a mode whose data is missing falls back to plain.

import { CSS_GRADIENT, scaleFor, uniformColors, vertexColors } from "./colormap.js";
import { DEFECT_LABELS, deg, fmt, pct } from "./format.js";
import { store } from "./store.js";

const $ = (id) => document.getElementById(id);
// Changes below these are round-off (float32 vertices over the wire): the distortion map
// stays dark instead of stretching them over the whole ramp.
const LENGTH_FLOOR = 1e-3;                // 0.1 %
const ANGLE_FLOOR = (0.1 * Math.PI) / 180; // 0.1°

function setLegend(title, scale, format, maxNote = "") {
  $("legend").hidden = false;
  $("legend-title").textContent = title;
  $("legend-ramp").style.background = CSS_GRADIENT;
  $("legend-min").textContent = format(scale.log ? scale.min : 0);
  $("legend-max").textContent = `${scale.clipped ? "≥ " : ""}${format(scale.max)}${maxNote}`;
}

/** Colour scale of the defect: exact forms on a fixed ramp from round-off to the tolerance
 * (so they stay dark), others from the tolerance up (only what fails lights up). */
function defectScale(r, values) {
  return r.integrable ? scaleFor(values, { log: true, min: 1e-17, max: r.tolerance })
    : scaleFor(values, { log: true, min: r.tolerance });
}

/** The integrability report the defect map shows: on a rebuilt surface, that of the forms
 * being rebuilt (the rebuilt surface's own forms are exact); otherwise the shown mesh's. */
export function shownDefects(s) {
  const rebuilt = s.source === "reconstruction" ? s.reconstruction?.integrability : null;
  return rebuilt ? { report: rebuilt, of: "the forms being rebuilt" }
    : s.integrability ? { report: s.integrability, of: "" } : null;
}

function drawColors(view, s) {
  if (!s.vertices) return;
  const mode = s.colorMode;
  $("color-mode").value = mode;
  view.setTexture(mode === "checker" && s.flat ? s.flat.texcoords : null);
  const defects = shownDefects(s);
  if (mode === "defect" && defects) {
    const r = defects.report;
    const values = r[s.defectPart];
    const scale = defectScale(r, values);
    view.setColors(vertexColors(values, scale));
    setLegend(`${DEFECT_LABELS[s.defectPart]} defect per vertex`
      + (defects.of ? ` of ${defects.of}` : "") + " (rad, log scale)"
      + (r.integrable ? ": all below the tolerance" : ""), scale, (x) => fmt(x, 2),
    r.integrable ? " (tolerance)" : "");
  } else if (mode === "distortion" && s.distortion) {
    const length = s.distortionKind === "length";
    const values = length ? s.distortion.vertexLength : s.distortion.vertexAngle;
    const scale = scaleFor(values, { floor: length ? LENGTH_FLOOR : ANGLE_FLOOR });
    view.setColors(vertexColors(values, scale));
    setLegend((length ? "Edge-length change (max per vertex)" : "Dihedral-angle change (max per vertex)")
      + (scale.quiet ? ": none" : ""), scale, length ? pct : deg);
  } else if (mode === "checker" && s.flat) {
    view.setColors(uniformColors(s.vertices.length / 3, [255, 255, 255]));
    $("legend").hidden = true;
  } else {
    $("legend").hidden = true;
    if (mode !== "plain") store.set({ colorMode: "plain" });  // draws again, plain
    else view.setColors(null);
  }
}

/** The colour menu offers what there is data for. */
function drawOptions(s) {
  for (const option of $("color-mode").options) {
    option.disabled = { plain: false, defect: !shownDefects(s), distortion: !s.distortion,
      checker: !s.flat }[option.value];
  }
}

export function installColorView(view) {
  store.subscribe(["integrability", "reconstruction", "source", "distortion", "flat"],
    drawOptions);
  store.subscribe(["topo", "colorMode", "integrability", "reconstruction", "source",
    "distortion", "flat", "defectPart", "distortionKind"], (s) => drawColors(view, s));
  $("color-mode").addEventListener("change", (event) => store.set({ colorMode: event.target.value }));
}
