// Picking on the 3D view: pointer positions to vertices (the nearest corner of the face
// under the pointer, the vertices in a box), points to screen positions, and whether a shape
// fits the canvas. Methods of MeshView (viewer.js), which mixes them in.

import * as THREE from "three";

export const picking = {
  ndc(clientX, clientY) {
    const rect = this.canvas.getBoundingClientRect();
    return new THREE.Vector2(((clientX - rect.left) / rect.width) * 2 - 1,
      -((clientY - rect.top) / rect.height) * 2 + 1);
  },

  /** The vertex of the picked face nearest to the hit point, or -1. */
  pickVertex(clientX, clientY) {
    if (!this.mesh) return -1;
    this.raycaster.setFromCamera(this.ndc(clientX, clientY), this.camera);
    const hit = this.raycaster.intersectObject(this.mesh, false)[0];
    if (!hit) return -1;
    const position = this.mesh.geometry.getAttribute("position");
    const corners = [hit.face.a, hit.face.b, hit.face.c];
    const p = new THREE.Vector3();
    let best = -1, bestDistance = Infinity;
    for (const v of corners) {
      const d = p.fromBufferAttribute(position, v).distanceToSquared(hit.point);
      if (d < bestDistance) {
        bestDistance = d;
        best = v;
      }
    }
    return best;
  },

  /** Whether every vertex (Float64Array(3n)) is in front of the camera and inside the
   * canvas, `top` pixels (an overlay such as the toolbar) excluded. */
  fits(vertices, { top = 0 } = {}) {
    const rect = this.canvas.getBoundingClientRect();
    this.camera.updateMatrixWorld();
    const m = new THREE.Matrix4().multiplyMatrices(this.camera.projectionMatrix,
      this.camera.matrixWorldInverse).elements;
    const yMax = 1 - (2 * top) / rect.height;
    for (let i = 0; i < vertices.length; i += 3) {
      const x = vertices[i], y = vertices[i + 1], z = vertices[i + 2];
      const w = m[3] * x + m[7] * y + m[11] * z + m[15];
      if (w <= 0) return false;
      const px = (m[0] * x + m[4] * y + m[8] * z + m[12]) / w;
      const py = (m[1] * x + m[5] * y + m[9] * z + m[13]) / w;
      if (px < -1 || px > 1 || py < -1 || py > yMax) return false;
    }
    return true;
  },

  /** Screen position (client pixels) of a point, and whether it faces the camera. */
  project(x, y, z) {
    const rect = this.canvas.getBoundingClientRect();
    this.camera.updateMatrixWorld();  // the camera may have moved since the last frame
    const v = new THREE.Vector3(x, y, z).project(this.camera);
    return { x: rect.left + ((v.x + 1) / 2) * rect.width,
      y: rect.top + ((1 - v.y) / 2) * rect.height };
  },

  /** Vertices inside a client-pixel rectangle; on closed meshes only those whose normal
   * faces the camera (open surfaces can be worked on from either side). */
  verticesInRect(left, top, right, bottom, { facing = true } = {}) {
    const geometry = this.mesh.geometry;
    const position = geometry.getAttribute("position"), normal = geometry.getAttribute("normal");
    const rect = this.canvas.getBoundingClientRect();
    this.camera.updateMatrixWorld();
    const p = new THREE.Vector3(), nrm = new THREE.Vector3(), eye = new THREE.Vector3();
    const out = [];
    for (let i = 0; i < position.count; i++) {
      p.fromBufferAttribute(position, i);
      nrm.fromBufferAttribute(normal, i);
      eye.copy(this.camera.position).sub(p);
      if (facing && nrm.dot(eye) <= 0) continue;
      p.project(this.camera);
      const x = rect.left + ((p.x + 1) / 2) * rect.width;
      const y = rect.top + ((1 - p.y) / 2) * rect.height;
      if (x >= left && x <= right && y >= top && y <= bottom && p.z < 1) out.push(i);
    }
    return out;
  }
};
