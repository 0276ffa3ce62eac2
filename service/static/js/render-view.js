// What the 3D and the flat views share: a renderer in a container that draws on demand
// (after a change; `paused` skips rendering altogether, which tests use to measure the page's
// own main-thread cost), the checkerboard and marker textures, and the geometry helpers.

import * as THREE from "three";

export function discTexture() {
  const size = 64, canvas = document.createElement("canvas");
  canvas.width = canvas.height = size;
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#fff";
  ctx.beginPath();
  ctx.arc(size / 2, size / 2, size / 2 - 2, 0, 2 * Math.PI);
  ctx.fill();
  ctx.strokeStyle = "rgba(0, 0, 0, 0.55)";
  ctx.lineWidth = 6;
  ctx.stroke();
  const texture = new THREE.CanvasTexture(canvas);
  texture.colorSpace = THREE.SRGBColorSpace;
  return texture;
}
export const CHECKER_REPEAT = 3;

export function checkerTexture() {
  const size = 256, cells = 8, canvas = document.createElement("canvas");
  canvas.width = canvas.height = size;
  const ctx = canvas.getContext("2d");
  for (let i = 0; i < cells; i++) {
    for (let j = 0; j < cells; j++) {
      ctx.fillStyle = (i + j) % 2 ? "#2c728e" : "#f3f5f8";
      ctx.fillRect((i * size) / cells, (j * size) / cells, size / cells, size / cells);
    }
  }
  const texture = new THREE.CanvasTexture(canvas);
  texture.wrapS = texture.wrapT = THREE.RepeatWrapping;
  texture.colorSpace = THREE.SRGBColorSpace;
  texture.anisotropy = 4;
  return texture;
}

/** Area-weighted vertex normals (Float32Array(3n)) of flat positions and faces: the same
 * as BufferGeometry.computeVertexNormals, on the arrays directly (no per-vertex calls). */
export function vertexNormals(p, index, out) {
  out.fill(0);
  for (let t = 0; t < index.length; t += 3) {
    const a = 3 * index[t], b = 3 * index[t + 1], c = 3 * index[t + 2];
    const ux = p[b] - p[a], uy = p[b + 1] - p[a + 1], uz = p[b + 2] - p[a + 2];
    const vx = p[c] - p[a], vy = p[c + 1] - p[a + 1], vz = p[c + 2] - p[a + 2];
    const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    out[a] += nx; out[a + 1] += ny; out[a + 2] += nz;
    out[b] += nx; out[b + 1] += ny; out[b + 2] += nz;
    out[c] += nx; out[c + 1] += ny; out[c + 2] += nz;
  }
  for (let i = 0; i < out.length; i += 3) {
    const len = Math.hypot(out[i], out[i + 1], out[i + 2]) || 1;
    out[i] /= len;
    out[i + 1] /= len;
    out[i + 2] /= len;
  }
  return out;
}

export function edgeIndex(edges) {
  return new THREE.BufferAttribute(edges instanceof Uint32Array ? edges : Uint32Array.from(edges), 1);
}

export class RenderView {
  constructor(container, { rotate = true } = {}) {
    this.container = container;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, alpha: true,
      preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.outputColorSpace = THREE.SRGBColorSpace;
    container.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.pending = false;
    this.observer = new ResizeObserver(() => this.resize());
    this.observer.observe(container);
    this.rotate = rotate;
  }

  get canvas() {
    return this.renderer.domElement;
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.container;
    if (!w || !h) return;
    this.renderer.setSize(w, h, true);
    this.updateCamera(w, h);
    this.request();
  }

  request() {
    if (this.pending || this.paused) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      if (!this.paused) this.renderer.render(this.scene, this.camera);
    });
  }
}

