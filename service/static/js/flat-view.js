// The flattened 2D layout of a mesh: its checkerboard, its edges, and its flipped faces in
// red, panned and zoomed (no rotation).

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { CHECKER_REPEAT, RenderView, checkerTexture, edgeIndex } from "./render-view.js";

export class FlatView extends RenderView {
  constructor(container) {
    super(container, { rotate: false });
    this.camera = new THREE.OrthographicCamera(-1, 1, 1, -1, -10, 10);
    this.controls = new OrbitControls(this.camera, this.canvas);
    this.controls.enableRotate = false;
    this.controls.screenSpacePanning = true;
    this.controls.mouseButtons = { LEFT: THREE.MOUSE.PAN, MIDDLE: THREE.MOUSE.DOLLY,
      RIGHT: THREE.MOUSE.PAN };
    this.controls.addEventListener("change", () => this.request());
    this.checker = checkerTexture();
    this.extent = 1;
    this.resize();
  }

  updateCamera(w, h) {
    const aspect = w / h, e = this.extent * 0.55;
    Object.assign(this.camera, aspect >= 1
      ? { left: -e * aspect, right: e * aspect, top: e, bottom: -e }
      : { left: -e, right: e, top: e / aspect, bottom: -e / aspect });
    this.camera.updateProjectionMatrix();
  }

  /** Show the layout: uv Float64Array(2n), faces, edges, flipped face ids; returns the
   * texture coordinates used (Float32Array(2n), 8 x CHECKER_REPEAT cells across). */
  show(uv, faces, edges, flipped) {
    for (const child of [...this.scene.children]) {
      this.scene.remove(child);
      child.geometry?.dispose();
    }
    const n = uv.length / 2;
    let minU = Infinity, minV = Infinity, maxU = -Infinity, maxV = -Infinity;
    for (let i = 0; i < n; i++) {
      minU = Math.min(minU, uv[2 * i]);
      maxU = Math.max(maxU, uv[2 * i]);
      minV = Math.min(minV, uv[2 * i + 1]);
      maxV = Math.max(maxV, uv[2 * i + 1]);
    }
    const size = Math.max(maxU - minU, maxV - minV) || 1;
    const cu = (minU + maxU) / 2, cv = (minV + maxV) / 2;
    const positions = new Float32Array(3 * n), texcoords = new Float32Array(2 * n);
    for (let i = 0; i < n; i++) {
      positions[3 * i] = (uv[2 * i] - cu) / size;
      positions[3 * i + 1] = (uv[2 * i + 1] - cv) / size;
      texcoords[2 * i] = ((uv[2 * i] - minU) / size) * CHECKER_REPEAT;
      texcoords[2 * i + 1] = ((uv[2 * i + 1] - minV) / size) * CHECKER_REPEAT;
    }
    const geometry = new THREE.BufferGeometry();
    const position = new THREE.BufferAttribute(positions, 3);
    geometry.setAttribute("position", position);
    geometry.setAttribute("uv", new THREE.BufferAttribute(texcoords, 2));
    geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(faces), 1));
    const sheet = new THREE.Mesh(geometry, new THREE.MeshBasicMaterial({ map: this.checker,
      side: THREE.DoubleSide }));
    const wire = new THREE.BufferGeometry();
    wire.setAttribute("position", position);
    wire.setIndex(edgeIndex(edges));
    const lines = new THREE.LineSegments(wire, new THREE.LineBasicMaterial({ color: 0x1f2933,
      transparent: true, opacity: 0.18 }));
    lines.position.z = 0.001;
    this.scene.add(sheet, lines);
    if (flipped.length) {
      const index = new Uint32Array(3 * flipped.length);
      flipped.forEach((t, k) => index.set(faces.subarray(3 * t, 3 * t + 3), 3 * k));
      const bad = new THREE.BufferGeometry();
      bad.setAttribute("position", position);
      bad.setIndex(new THREE.BufferAttribute(index, 1));
      const flips = new THREE.Mesh(bad, new THREE.MeshBasicMaterial({ color: 0xe02424,
        side: THREE.DoubleSide, transparent: true, opacity: 0.85 }));
      flips.position.z = 0.002;
      this.scene.add(flips);
    }
    this.extent = 1;
    this.controls.target.set(0, 0, 0);
    this.camera.position.set(0, 0, 5);
    this.camera.zoom = 1;
    this.controls.update();
    this.resize();
    return texcoords;
  }
}
