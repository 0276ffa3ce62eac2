// Deformation handles as data: a handle is a set of vertices moved rigidly by a pivot (a
// three.js Object3D the gizmo drags); its targets and rotations make the deformation
// set-up that deform.js sends. No DOM.

import * as THREE from "three";
import { facesAround } from "./mesh.js";
import { state } from "./store.js";

const HANDLE_COLORS = [0xe4572e, 0x2e86ab, 0x9c27b0, 0xff9f1c, 0x43aa8b, 0xd81159];

/** The number of the next handle: one more than the mesh's highest (a fresh mesh starts at
 * 1: the numbers name the handles of this mesh, not every handle the page ever made). */
export function nextHandleNumber(handles = state.handles) {
  return handles.reduce((top, h) => Math.max(top, h.id), 0) + 1;
}

/** A handle of `vertices` (ids) of the shown shape, its pivot at their centre, numbered
 * `number`. */
export function newHandle(vertices, number = nextHandleNumber()) {
  const start = new Float64Array(3 * vertices.length);
  const center = new THREE.Vector3();
  vertices.forEach((v, k) => {
    start.set(state.vertices.subarray(3 * v, 3 * v + 3), 3 * k);
    center.x += state.vertices[3 * v] / vertices.length;
    center.y += state.vertices[3 * v + 1] / vertices.length;
    center.z += state.vertices[3 * v + 2] / vertices.length;
  });
  const pivot = new THREE.Object3D();
  pivot.position.copy(center);
  return { id: number, vertices, start, center: center.clone(), pivot,
    color: HANDLE_COLORS[(number - 1) % HANDLE_COLORS.length], rotationFaces: [] };
}

/** Targets of all handle vertices (Float64Array), and the rotation (3x3 rows) of each
 * rotation group. */
export function handleTargets() {
  const count = state.handles.reduce((s, h) => s + h.vertices.length, 0);
  const positions = new Float64Array(3 * count);
  const rotations = [];
  const offset = new THREE.Vector3(), m = new THREE.Matrix4();
  let k = 0;
  for (const h of state.handles) {
    for (let i = 0; i < h.vertices.length; i++) {
      offset.set(h.start[3 * i], h.start[3 * i + 1], h.start[3 * i + 2]).sub(h.center)
        .applyQuaternion(h.pivot.quaternion).add(h.pivot.position);
      positions.set([offset.x, offset.y, offset.z], 3 * k++);
    }
    if (h.rotationFaces.length) {
      const e = m.makeRotationFromQuaternion(h.pivot.quaternion).elements;
      rotations.push([[e[0], e[4], e[8]], [e[1], e[5], e[9]], [e[2], e[6], e[10]]]);
    }
  }
  return { positions, rotations };
}

/** The deformation set-up (deform.js) of the current handles and options. */
export function setupFor() {
  const taken = new Set();
  for (const h of state.handles) h.rotationFaces = facesAround(h.vertices, state.faces, taken);
  const { positions, rotations } = handleTargets();
  return {
    rest: state.rest, faces: state.faces,
    handles: state.handles.flatMap((h) => h.vertices),
    rotationGroups: state.handles.filter((h) => h.rotationFaces.length).map((h) => h.rotationFaces),
    orthonormalize: state.orthonormalize,
    refine: state.refineDrags,
    initialPositions: positions, initialRotations: rotations,
  };
}

/** The current shape becomes the rest shape of the next session (handles keep their
 * place); returns the new rest shape. */
export function bake() {
  const rest = state.vertices.slice();
  const { positions } = handleTargets();
  let k = 0;
  for (const h of state.handles) {
    h.start = positions.slice(3 * k, 3 * (k + h.vertices.length));
    k += h.vertices.length;
    h.center.copy(h.pivot.position);
    h.pivot.quaternion.identity();
  }
  return rest;
}
