// The 3D view of the mesh (three.js): lit, orbit controls, up axis, grid and axes,
// wireframe, vertex colours, selection and handle markers, transform gizmo; picking is
// picking.js's.
// Rendering is on demand (render-view.js), which keeps a software-rendered browser idle.
// Materials are made once: an update never recompiles a shader.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { TransformControls } from "three/addons/controls/TransformControls.js";
import { picking } from "./picking.js";
import { RenderView, checkerTexture, discTexture, edgeIndex, vertexNormals } from "./render-view.js";

const BASE_COLOR = [200, 206, 214];
const SELECTION_COLOR = 0xffb000;
const MARKER_PIXELS = 9;
// Fit leaves the top of the canvas that the floating toolbar covers (plus this gap, pixels),
// and, while the gizmo is shown, the reach of its arrows and rings above a handle at the top
// (about 0.13 of the canvas height at the gizmo's size 0.9), as a fraction of the height.
const TOOLBAR_GAP = 8;
const GIZMO_REACH = 0.14;
const MAX_INSET = 0.45;

/** Unit vector of an up-axis name: "+y", "-z", ... */
export function axisVector(name) {
  const sign = name[0] === "-" ? -1 : 1;
  return new THREE.Vector3().setComponent("xyz".indexOf(name[1]), sign);
}

export class MeshView extends RenderView {
  constructor(container) {
    super(container);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
    this.camera.position.set(0, 0, 3);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x5a6470, 1.6));
    const key = new THREE.DirectionalLight(0xffffff, 1.8);
    key.position.set(0.6, 1.0, 0.8);
    this.camera.add(key);
    this.scene.add(this.camera);

    this.controls = new OrbitControls(this.camera, this.canvas);
    this.controls.addEventListener("change", () => this.request());

    this.material = new THREE.MeshStandardMaterial({ vertexColors: true, roughness: 0.62,
      metalness: 0.0, side: THREE.DoubleSide, polygonOffset: true, polygonOffsetFactor: 1,
      polygonOffsetUnits: 1 });
    this.wireMaterial = new THREE.LineBasicMaterial({ color: 0x1f2933, transparent: true,
      opacity: 0.35 });
    this.checker = checkerTexture();

    // Selection and handle vertices: one Points object, a fixed pixel size (a big handle is a
    // field of dots, not a carpet of spheres), geometry reused until it needs more room;
    // drawn over the surface, so a handle stays visible where the mesh would hide it.
    this.markerMaterial = new THREE.PointsMaterial({ size: MARKER_PIXELS, sizeAttenuation: false,
      vertexColors: true, map: discTexture(), alphaTest: 0.5, depthTest: false,
      transparent: true });
    this.markers = new THREE.Points(new THREE.BufferGeometry(), this.markerMaterial);
    this.markers.renderOrder = 10;
    this.markers.frustumCulled = false;
    this.markerCapacity = 0;
    this.scene.add(this.markers);
    this.up = new THREE.Vector3(0, 1, 0);
    this.helpers = new THREE.Group();
    this.helpers.visible = false;
    this.scene.add(this.helpers);

    this.gizmo = new TransformControls(this.camera, this.canvas);
    this.gizmo.setSize(0.9);
    this.gizmo.addEventListener("dragging-changed", (e) => {
      this.controls.enabled = !e.value;
    });
    this.gizmo.addEventListener("change", () => this.request());
    this.scene.add(this.gizmo.getHelper());

    this.raycaster = new THREE.Raycaster();
    this.mesh = null;
    this.resize();
  }

  /** Which way is up (a unit Vector3 in mesh coordinates); the orbit keeps it vertical. */
  setUp(up, { refit = true } = {}) {
    this.up.copy(up).normalize();
    this.camera.up.copy(this.up);
    // OrbitControls caches the rotation from camera.up to +Y when it is made.
    this.controls._quat.setFromUnitVectors(this.camera.up, new THREE.Vector3(0, 1, 0));
    this.controls._quatInverse.copy(this.controls._quat).invert();
    if (this.mesh && refit) {
      this.buildHelpers();
      this.frame();
    }
  }

  setHelpers(visible) {
    this.helpers.visible = visible;
    this.request();
  }

  /** A grid on the ground (the plane through the lowest point, normal to up) and axes at
   * its corner, sized to the mesh. */
  buildHelpers() {
    for (const child of [...this.helpers.children]) {
      this.helpers.remove(child);
      child.geometry.dispose();
      child.material.dispose();
    }
    const box = new THREE.Box3().setFromBufferAttribute(this.mesh.geometry.getAttribute("position"));
    const center = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3());
    const extent = Math.max(size.x, size.y, size.z) || 1;
    const step = 10 ** Math.floor(Math.log10(extent / 2));
    const span = Math.ceil((1.6 * extent) / step) * step;
    const grid = new THREE.GridHelper(span, Math.round(span / step), 0x7b8794, 0xc5ccd5);
    grid.quaternion.setFromUnitVectors(new THREE.Vector3(0, 1, 0), this.up);
    const low = -0.5 * (Math.abs(this.up.x) * size.x + Math.abs(this.up.y) * size.y
      + Math.abs(this.up.z) * size.z);
    grid.position.copy(center).addScaledVector(this.up, low);
    const axes = new THREE.AxesHelper(0.3 * extent);
    axes.position.copy(grid.position);
    axes.material.depthTest = false;
    axes.renderOrder = 5;
    this.helpers.add(grid, axes);
    this.gridStep = step;
  }

  updateCamera(w, h) {
    this.camera.aspect = w / h;
    // The view's centre is the centre of the part of the canvas below the toolbar.
    const inset = this.inset ?? 0;
    if (inset) this.camera.setViewOffset(w, h, 0, -inset / 2, w, h);
    else this.camera.clearViewOffset();
    this.camera.updateProjectionMatrix();
  }

  /** Pixels at the top of the canvas that Fit leaves free: what the floating toolbar covers,
   * and the gizmo's reach while it is shown. */
  topInset() {
    const canvas = this.canvas.getBoundingClientRect();
    const bar = this.container.querySelector(".view-toolbar");
    const covered = bar ? bar.getBoundingClientRect().bottom - canvas.top + TOOLBAR_GAP : 0;
    const gizmo = this.gizmo?.object ? GIZMO_REACH * canvas.height : 0;
    return Math.max(0, Math.min(covered + gizmo, MAX_INSET * canvas.height));
  }

  /** Replace the mesh: vertices Float64Array(3n), faces Uint32Array(3m), edges Uint32Array(2E). */
  setMesh(vertices, faces, edges) {
    if (this.mesh) {
      this.scene.remove(this.mesh, this.wire);
      this.mesh.geometry.dispose();
      this.wire.geometry.dispose();
    }
    const n = vertices.length / 3;
    const geometry = new THREE.BufferGeometry();
    const position = new THREE.BufferAttribute(new Float32Array(vertices), 3);
    position.setUsage(THREE.DynamicDrawUsage);
    geometry.setAttribute("position", position);
    geometry.setAttribute("color", new THREE.BufferAttribute(new Float32Array(3 * n), 3));
    geometry.setAttribute("uv", new THREE.BufferAttribute(new Float32Array(2 * n), 2));
    geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(faces), 1));
    const normal = new THREE.BufferAttribute(vertexNormals(position.array, faces,
      new Float32Array(3 * n)), 3);
    normal.setUsage(THREE.DynamicDrawUsage);
    geometry.setAttribute("normal", normal);
    geometry.computeBoundingSphere();
    this.mesh = new THREE.Mesh(geometry, this.material);
    const wireGeometry = new THREE.BufferGeometry();
    wireGeometry.setAttribute("position", position);
    wireGeometry.setIndex(edgeIndex(edges));
    this.wire = new THREE.LineSegments(wireGeometry, this.wireMaterial);
    this.wire.visible = !!this.wireVisible;
    this.scene.add(this.mesh, this.wire);
    this.setColors(null);
    this.setMarkers(vertices, [], []);
    this.buildHelpers();
    this.frame();
  }

  /** The direction to look from, level with the up axis and a little above: the mean outward
   * normal of an open surface when it is not vertical, else along the thinnest horizontal
   * side of the bounding box (a torus is seen through its hole, a figure from the front). */
  viewDirection() {
    const position = this.mesh.geometry.getAttribute("position");
    const index = this.mesh.geometry.getIndex().array;
    const p = position.array;
    let sx = 0, sy = 0, sz = 0, area = 0;
    for (let t = 0; t < index.length; t += 3) {
      const a = 3 * index[t], b = 3 * index[t + 1], c = 3 * index[t + 2];
      const ux = p[b] - p[a], uy = p[b + 1] - p[a + 1], uz = p[b + 2] - p[a + 2];
      const vx = p[c] - p[a], vy = p[c + 1] - p[a + 1], vz = p[c + 2] - p[a + 2];
      const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
      sx += nx;
      sy += ny;
      sz += nz;
      area += Math.hypot(nx, ny, nz);
    }
    const up = this.up;
    const normal = new THREE.Vector3(sx, sy, sz);
    const level = normal.clone().addScaledVector(up, -normal.dot(up));
    let direction;
    if (level.length() > 0.3 * area) {
      direction = level.normalize();
    } else {
      const box = new THREE.Box3().setFromBufferAttribute(position);
      const size = box.getSize(new THREE.Vector3());
      let best = -1;
      for (let k = 0; k < 3; k++) {
        if (Math.abs(up.getComponent(k)) > 0.5) continue;
        if (best < 0 || size.getComponent(k) < size.getComponent(best)) best = k;
      }
      direction = new THREE.Vector3().setComponent(best, 1);
      // An open surface facing up or down (a terrain): look at its front side from above.
      if (normal.length() > 0.3 * area && normal.dot(up) < 0) direction.negate();
    }
    const lift = normal.length() > 0.3 * area && Math.abs(normal.dot(up)) > 0.7 * normal.length()
      ? Math.sign(normal.dot(up)) * 1.0 : 0.35;
    return direction.addScaledVector(up, lift).normalize();
  }

  /** Fit the mesh in the view: from its best side, or (keep) from the current direction. */
  frame({ keep = false } = {}) {
    const sphere = this.mesh.geometry.boundingSphere;
    this.radius = sphere.radius || 1;
    const height = this.canvas.getBoundingClientRect().height;
    if (height) {
      this.inset = this.topInset();
      this.updateCamera(this.canvas.clientWidth, height);
    }
    // The sphere fits the free part of the canvas: its height is (height - inset).
    const vertical = Math.atan(Math.tan(THREE.MathUtils.degToRad(this.camera.fov / 2))
      * (height ? (height - (this.inset ?? 0)) / height : 1));
    const horizontal = Math.atan(Math.tan(vertical) * this.camera.aspect);
    const distance = (this.radius / Math.sin(Math.min(vertical, horizontal))) * 1.08;
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    const direction = keep
      ? this.camera.position.clone().sub(this.controls.target).normalize()
      : this.viewDirection();
    this.camera.up.copy(this.up);
    this.camera.position.copy(sphere.center).addScaledVector(direction, distance);
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(sphere.center);
    this.controls.update();
    this.request();
  }

  updatePositions(vertices) {
    const position = this.mesh.geometry.getAttribute("position");
    position.array.set(vertices);
    position.needsUpdate = true;
    const normal = this.mesh.geometry.getAttribute("normal");
    vertexNormals(position.array, this.mesh.geometry.getIndex().array, normal.array);
    normal.needsUpdate = true;
    this.mesh.geometry.computeBoundingSphere();
    this.request();
  }

  /** Linear RGB Float32Array(3n), or null for the plain material colour. */
  setColors(colors) {
    const attribute = this.mesh.geometry.getAttribute("color");
    if (colors) attribute.array.set(colors);
    else {
      const c = new THREE.Color().setRGB(...BASE_COLOR.map((x) => x / 255), THREE.SRGBColorSpace);
      for (let i = 0; i < attribute.count; i++) attribute.setXYZ(i, c.r, c.g, c.b);
    }
    attribute.needsUpdate = true;
    this.request();
  }

  /** Checkerboard texture through uv (Float32Array(2n)), or null to remove it. */
  setTexture(uv) {
    const map = uv ? this.checker : null;
    if (uv && this.uvShown !== uv) {
      const attribute = this.mesh.geometry.getAttribute("uv");
      attribute.array.set(uv);
      attribute.needsUpdate = true;
    }
    this.uvShown = uv;
    if (this.material.map !== map) {
      // A map changes the shader: compiled once per state, switched only when it changes.
      this.material.map = map;
      this.material.needsUpdate = true;
    }
    this.request();
  }

  setWireframe(visible) {
    this.wireVisible = visible;
    if (this.wire) this.wire.visible = visible;
    this.request();
  }

  /** Dots at selected vertices and at handle vertices (one colour per handle). */
  setMarkers(vertices, selection, handles) {
    const groups = [{ ids: selection, color: SELECTION_COLOR }, ...handles.map((h) => ({
      ids: h.vertices, color: h.color }))];
    const count = groups.reduce((s, g) => s + g.ids.length, 0);
    let geometry = this.markers.geometry;
    if (count > this.markerCapacity || !this.markerCapacity) {
      geometry.dispose();
      this.markerCapacity = Math.max(64, 2 * count);
      geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(
        new Float32Array(3 * this.markerCapacity), 3).setUsage(THREE.DynamicDrawUsage));
      geometry.setAttribute("color", new THREE.BufferAttribute(
        new Float32Array(3 * this.markerCapacity), 3).setUsage(THREE.DynamicDrawUsage));
      this.markers.geometry = geometry;
    }
    const position = geometry.getAttribute("position").array;
    const colors = geometry.getAttribute("color").array;
    const c = new THREE.Color();
    let k = 0;
    for (const { ids, color } of groups) {
      c.setHex(color);
      for (const v of ids) {
        position[3 * k] = vertices[3 * v];
        position[3 * k + 1] = vertices[3 * v + 1];
        position[3 * k + 2] = vertices[3 * v + 2];
        colors[3 * k] = c.r;
        colors[3 * k + 1] = c.g;
        colors[3 * k + 2] = c.b;
        k++;
      }
    }
    geometry.getAttribute("position").needsUpdate = true;
    geometry.getAttribute("color").needsUpdate = true;
    geometry.setDrawRange(0, count);
    this.markers.visible = count > 0;
    this.request();
  }

  attachGizmo(object) {
    if (object) {
      if (!object.parent) this.scene.add(object);
      this.gizmo.attach(object);
    } else {
      this.gizmo.detach();
    }
    this.request();
  }

  gizmoActive() {
    return this.gizmo.dragging || this.gizmo.axis !== null;
  }
}

// Screen <-> mesh (picking.js): the methods that map pointer positions to vertices.
Object.assign(MeshView.prototype, picking);
