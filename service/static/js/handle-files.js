// Handle sets as files: the JSON that `ffs deform --handles` reads (the API's `handles` list
// with each handle vertex's target, and `rotations` for the faces a handle turns), plus
// `groups` (the page's handles: their vertices and rotation, which ffs ignores) so that an
// exported set imports back as the same handles. No DOM.

import * as THREE from "three";
import { deformParams } from "./deform.js";
import { handleTargets, newHandle, setupFor } from "./handles.js";
import { state } from "./store.js";

/** The current handles as a document: {handles, rotations?, groups}. */
export function handleSetDocument() {
  const setup = setupFor();  // first: it groups the faces that the rotations turn
  const { positions, rotations } = handleTargets();
  const { handles, rotations: turned } = deformParams(setup, positions, rotations);
  const m = new THREE.Matrix4();
  const groups = state.handles.map((h) => {
    const e = m.makeRotationFromQuaternion(h.pivot.quaternion).elements;
    return { vertices: [...h.vertices],
      rotation: [[e[0], e[4], e[8]], [e[1], e[5], e[9]], [e[2], e[6], e[10]]] };
  });
  return { handles, ...(turned ? { rotations: turned } : {}), groups };
}

/** A problem with an imported document, in words (the page shows it as an error). */
export class HandleFileError extends Error {}

function targetsOf(doc, n) {
  const list = Array.isArray(doc) ? doc : doc?.handles;
  if (!Array.isArray(list) || !list.length) {
    throw new HandleFileError('expected a non-empty list [{"vertex": i, "position": [x, y, z]}, ...] '
      + 'or an object with "handles" (what Export handles and ffs deform --handles use)');
  }
  const targets = new Map();
  list.forEach((h, i) => {
    const ok = h && Number.isInteger(h.vertex) && Array.isArray(h.position)
      && h.position.length === 3 && h.position.every(Number.isFinite);
    if (!ok) throw new HandleFileError(`handles[${i}]: expected {"vertex": integer, "position": [x, y, z]}`);
    if (h.vertex < 0 || h.vertex >= n) {
      throw new HandleFileError(`handles[${i}]: vertex ${h.vertex} is not a vertex of this mesh (0 to ${n - 1})`);
    }
    targets.set(h.vertex, h.position);
  });
  return targets;
}

/** Groups of handle vertices without a saved grouping: those that move by the same vector. */
function groupsByDisplacement(targets) {
  const size = state.meanEdge || 1;
  const byKey = new Map();
  for (const [v, p] of targets) {
    const key = [0, 1, 2].map((c) => Math.round((p[c] - state.vertices[3 * v + c]) / (1e-6 * size)))
      .join(",");
    if (!byKey.has(key)) byKey.set(key, []);
    byKey.get(key).push(v);
  }
  return [...byKey.values()].map((vertices) => ({ vertices, rotation: null }));
}

/** Page handles (from newHandle) placed at a document's targets: each group's pivot takes
 * the mean of its targets and its saved rotation (a group moves rigidly). */
export function handlesFromDocument(doc) {
  const n = state.vertices.length / 3;
  const targets = targetsOf(doc, n);
  const groups = Array.isArray(doc?.groups) ? doc.groups : groupsByDisplacement(targets);
  const seen = new Set();
  const handles = groups.map((group, g) => {
    const vertices = group?.vertices;
    if (!Array.isArray(vertices) || !vertices.length
        || !vertices.every((v) => targets.has(v) && !seen.has(v))) {
      throw new HandleFileError(`groups[${g}]: expected {"vertices": [...]} of handle vertices, `
        + "each in one group");
    }
    vertices.forEach((v) => seen.add(v));
    const handle = newHandle(vertices, g + 1);
    const mean = new THREE.Vector3();
    for (const v of vertices) mean.add(new THREE.Vector3(...targets.get(v)));
    handle.pivot.position.copy(mean.divideScalar(vertices.length));
    const r = group.rotation;
    if (Array.isArray(r) && r.length === 3) {
      const m = new THREE.Matrix4().set(r[0][0], r[0][1], r[0][2], 0, r[1][0], r[1][1], r[1][2], 0,
        r[2][0], r[2][1], r[2][2], 0, 0, 0, 0, 1);
      handle.pivot.quaternion.setFromRotationMatrix(m);
    }
    return handle;
  });
  if (seen.size !== targets.size) {
    throw new HandleFileError(`${targets.size - seen.size} handle vertices are in no group`);
  }
  return handles;
}
