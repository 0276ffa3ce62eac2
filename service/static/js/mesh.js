// Mesh utilities on flat typed arrays: vertices Float64Array(3n), faces Uint32Array(3m).
// Edges follow the API's convention: unique undirected [i, j], i < j, sorted
// lexicographically; dihedral angles are signed like solver/forms.py (positive where convex).

export function flatten3(rows, Type = Float64Array) {
  const out = new Type(rows.length * 3);
  for (let i = 0; i < rows.length; i++) {
    const r = rows[i];
    out[3 * i] = r[0];
    out[3 * i + 1] = r[1];
    out[3 * i + 2] = r[2];
  }
  return out;
}

export function rows3(flat) {
  const out = new Array(flat.length / 3);
  for (let i = 0; i < out.length; i++) out[i] = [flat[3 * i], flat[3 * i + 1], flat[3 * i + 2]];
  return out;
}

/** Edge list and, per edge, the face left of i -> j and the face on the other side (-1). */
export function topology(faces, nVertices) {
  const m = faces.length / 3;
  const index = new Map();
  const keys = [];
  for (let t = 0; t < m; t++) {
    for (let k = 0; k < 3; k++) {
      const a = faces[3 * t + k], b = faces[3 * t + ((k + 1) % 3)];
      const key = Math.min(a, b) * nVertices + Math.max(a, b);
      if (!index.has(key)) {
        index.set(key, keys.length);
        keys.push(key);
      }
    }
  }
  const order = Float64Array.from(keys).sort();
  const E = order.length;
  const edges = new Uint32Array(2 * E);
  const rank = new Map();
  for (let e = 0; e < E; e++) {
    const key = order[e];
    edges[2 * e] = Math.floor(key / nVertices);
    edges[2 * e + 1] = key % nVertices;
    rank.set(key, e);
  }
  const left = new Int32Array(E).fill(-1), right = new Int32Array(E).fill(-1);
  for (let t = 0; t < m; t++) {
    for (let k = 0; k < 3; k++) {
      const a = faces[3 * t + k], b = faces[3 * t + ((k + 1) % 3)];
      const e = rank.get(Math.min(a, b) * nVertices + Math.max(a, b));
      if (a < b) left[e] = t;
      else right[e] = t;
    }
  }
  return { nVertices, nFaces: m, edges, left, right };
}

function faceNormals(vertices, faces) {
  const m = faces.length / 3;
  const normals = new Float64Array(3 * m);
  for (let t = 0; t < m; t++) {
    const a = 3 * faces[3 * t], b = 3 * faces[3 * t + 1], c = 3 * faces[3 * t + 2];
    const ux = vertices[b] - vertices[a], uy = vertices[b + 1] - vertices[a + 1];
    const uz = vertices[b + 2] - vertices[a + 2];
    const vx = vertices[c] - vertices[a], vy = vertices[c + 1] - vertices[a + 1];
    const vz = vertices[c + 2] - vertices[a + 2];
    let nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    const len = Math.hypot(nx, ny, nz) || 1;
    normals[3 * t] = nx / len;
    normals[3 * t + 1] = ny / len;
    normals[3 * t + 2] = nz / len;
  }
  return normals;
}

/** Edge lengths and signed dihedral angles (0 on boundary edges), aligned with topo.edges. */
export function forms(vertices, faces, topo) {
  const E = topo.edges.length / 2;
  const lengths = new Float64Array(E), angles = new Float64Array(E);
  const normals = faceNormals(vertices, faces);
  for (let e = 0; e < E; e++) {
    const i = 3 * topo.edges[2 * e], j = 3 * topo.edges[2 * e + 1];
    const dx = vertices[j] - vertices[i], dy = vertices[j + 1] - vertices[i + 1];
    const dz = vertices[j + 2] - vertices[i + 2];
    const len = Math.hypot(dx, dy, dz);
    lengths[e] = len;
    const l = topo.left[e], r = topo.right[e];
    if (l < 0 || r < 0 || len === 0) continue;
    const lx = normals[3 * l], ly = normals[3 * l + 1], lz = normals[3 * l + 2];
    const rx = normals[3 * r], ry = normals[3 * r + 1], rz = normals[3 * r + 2];
    const cx = ly * rz - lz * ry, cy = lz * rx - lx * rz, cz = lx * ry - ly * rx;
    const phi = Math.atan2((cx * dx + cy * dy + cz * dz) / len, lx * rx + ly * ry + lz * rz);
    angles[e] = phi <= -Math.PI ? Math.PI : phi;
  }
  return { lengths, angles };
}

function wrap(angle) {
  let a = ((angle + Math.PI) % (2 * Math.PI) + 2 * Math.PI) % (2 * Math.PI) - Math.PI;
  return a <= -Math.PI ? Math.PI : a;
}

/** |values| as a new Float64Array. */
function absolute(values) {
  const out = new Float64Array(values.length);
  for (let i = 0; i < out.length; i++) out[i] = Math.abs(values[i]);
  return out;
}

/** Rearranges `a` (Float64Array) so that a[k] is its k-th smallest value, smaller ones before
 * it and larger ones after (Hoare's selection: linear time on average, no full sort). */
export function select(a, k) {
  let lo = 0, hi = a.length - 1;
  while (hi > lo) {
    const pivot = a[(lo + hi) >> 1];
    let i = lo, j = hi;
    while (i <= j) {
      while (a[i] < pivot) i++;
      while (a[j] > pivot) j--;
      if (i <= j) {
        const t = a[i];
        a[i] = a[j];
        a[j] = t;
        i++;
        j--;
      }
    }
    if (k <= j) hi = j;
    else if (k >= i) lo = i;
    else break;
  }
  return a[k];
}

/** The q-quantile of |values| with numpy's default (linear interpolation between the closest
 * ranks). */
export function absQuantile(values, q) {
  const n = values.length;
  if (!n) return 0;
  const a = absolute(values);
  const pos = q * (n - 1), lo = Math.floor(pos);
  const low = select(a, lo);
  if (lo + 1 >= n || pos === lo) return low;
  let high = Infinity;  // the next order statistic: the smallest value right of lo
  for (let i = lo + 1; i < n; i++) if (a[i] < high) high = a[i];
  return low + (high - low) * (pos - lo);
}

export function summary(values) {
  const n = values.length;
  if (!n) return { mean: 0, rms: 0, max: 0, p95: 0 };
  let sum = 0, sq = 0, max = 0;
  for (let i = 0; i < n; i++) {
    const v = Math.abs(values[i]);
    sum += v;
    sq += v * v;
    if (v > max) max = v;
  }
  return { mean: sum / n, rms: Math.sqrt(sq / n), max, p95: absQuantile(values, 0.95) };
}

/**
 * Distortion of the current forms relative to reference forms (solver.metrics conventions):
 * per edge the relative length change and the wrapped dihedral change, per vertex the max
 * |change| over its edges.
 */
export function distortion(reference, current, topo) {
  const E = reference.lengths.length;
  const length = new Float64Array(E), angle = new Float64Array(E);
  const vertexLength = new Float64Array(topo.nVertices);
  const vertexAngle = new Float64Array(topo.nVertices);
  for (let e = 0; e < E; e++) {
    length[e] = current.lengths[e] / reference.lengths[e] - 1;
    angle[e] = wrap(current.angles[e] - reference.angles[e]);
    const i = topo.edges[2 * e], j = topo.edges[2 * e + 1];
    const a = Math.abs(length[e]), b = Math.abs(angle[e]);
    if (a > vertexLength[i]) vertexLength[i] = a;
    if (a > vertexLength[j]) vertexLength[j] = a;
    if (b > vertexAngle[i]) vertexAngle[i] = b;
    if (b > vertexAngle[j]) vertexAngle[j] = b;
  }
  return {
    length, angle, vertexLength, vertexAngle,
    lengthSummary: summary(length), angleSummary: summary(angle),
  };
}

/** Counts of |values| in `bins` equal bins over [0, max]. */
export function histogram(values, bins = 20) {
  let top = 0;
  for (const v of values) top = Math.max(top, Math.abs(v));
  top = top || 1;
  const counts = new Array(bins).fill(0);
  for (const v of values) counts[Math.min(bins - 1, Math.floor((Math.abs(v) / top) * bins))]++;
  return { counts, top };
}

export function bounds(vertices) {
  const min = [Infinity, Infinity, Infinity], max = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < vertices.length; i += 3) {
    for (let k = 0; k < 3; k++) {
      min[k] = Math.min(min[k], vertices[i + k]);
      max[k] = Math.max(max[k], vertices[i + k]);
    }
  }
  return { min, max };
}

/** Faces touching any of `vertices`, skipping faces in `taken` (a Set, updated). */
export function facesAround(vertexIds, faces, taken) {
  const inside = new Set(vertexIds);
  const out = [];
  for (let t = 0; t < faces.length / 3; t++) {
    if (taken.has(t)) continue;
    if (inside.has(faces[3 * t]) || inside.has(faces[3 * t + 1]) || inside.has(faces[3 * t + 2])) {
      out.push(t);
      taken.add(t);
    }
  }
  return out;
}

export function meanEdgeLength(vertices, edges) {
  let sum = 0;
  const E = edges.length / 2;
  for (let e = 0; e < E; e++) {
    const i = 3 * edges[2 * e], j = 3 * edges[2 * e + 1];
    sum += Math.hypot(vertices[j] - vertices[i], vertices[j + 1] - vertices[i + 1],
      vertices[j + 2] - vertices[i + 2]);
  }
  return E ? sum / E : 0;
}

/**
 * Everything the page derives from a mesh once: flat vertices Float64Array(3n) and faces
 * Uint32Array(3m) (from nested rows or flat arrays), the edge topology, the reference forms
 * (the distortion reference), the mean edge length and the number of boundary edges.
 */
export function prepareMesh(vertices, faces) {
  const v = vertices instanceof Float64Array ? vertices : flatten3(vertices);
  const f = faces instanceof Uint32Array ? faces : flatten3(faces, Uint32Array);
  const topo = topology(f, v.length / 3);
  let boundaryEdges = 0;
  for (let e = 0; e < topo.left.length; e++) {
    if (topo.right[e] < 0 || topo.left[e] < 0) boundaryEdges++;
  }
  return { vertices: v, faces: f, topo, reference: forms(v, f, topo),
    meanEdge: meanEdgeLength(v, topo.edges), boundaryEdges };
}

/** The buffers of a prepared mesh, for postMessage's transfer list. */
export function preparedBuffers(p) {
  return [p.vertices.buffer, p.faces.buffer, p.topo.edges.buffer, p.topo.left.buffer,
    p.topo.right.buffer, p.reference.lengths.buffer, p.reference.angles.buffer];
}

/** Eigenvector of the largest eigenvalue of a symmetric 4x4 matrix (cyclic Jacobi). */
function largestEigenvector4(matrix) {
  const a = matrix.map((row) => row.slice());
  const v = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
  const scale = a.reduce((s, row) => s + row.reduce((t, x) => t + x * x, 0), 0);
  for (let sweep = 0; sweep < 50; sweep++) {
    let off = 0;
    for (let p = 0; p < 4; p++) for (let q = p + 1; q < 4; q++) off += a[p][q] ** 2;
    if (off <= 1e-30 * scale) break;
    for (let p = 0; p < 4; p++) {
      for (let q = p + 1; q < 4; q++) {
        if (a[p][q] === 0) continue;
        const theta = (a[q][q] - a[p][p]) / (2 * a[p][q]);
        const t = (theta >= 0 ? 1 : -1) / (Math.abs(theta) + Math.sqrt(theta * theta + 1));
        const c = 1 / Math.sqrt(t * t + 1), s = t * c;
        for (const m of [a, v]) {  // columns p, q of A and of V: times the rotation
          for (let k = 0; k < 4; k++) {
            const kp = m[k][p], kq = m[k][q];
            m[k][p] = c * kp - s * kq;
            m[k][q] = s * kp + c * kq;
          }
        }
        for (let k = 0; k < 4; k++) {  // rows p, q of A
          const pk = a[p][k], qk = a[q][k];
          a[p][k] = c * pk - s * qk;
          a[q][k] = s * pk + c * qk;
        }
      }
    }
  }
  let best = 0;
  for (let k = 1; k < 4; k++) if (a[k][k] > a[best][best]) best = k;
  return v.map((row) => row[best]);
}

/**
 * `vertices` (Float64Array(3n)) moved by the rotation and translation that best fit them
 * onto `target` (Float64Array(3n), the same vertices in the same order), in the
 * least-squares sense (Horn's unit-quaternion method: no reflection, no scaling). Returns a
 * new Float64Array(3n).
 */
export function rigidAlign(vertices, target) {
  const n = vertices.length / 3;
  const ca = [0, 0, 0], cb = [0, 0, 0];
  for (let i = 0; i < n; i++) {
    for (let k = 0; k < 3; k++) {
      ca[k] += vertices[3 * i + k] / n;
      cb[k] += target[3 * i + k] / n;
    }
  }
  const S = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];  // S[a][b] = sum of x_a y_b, centred
  for (let i = 0; i < n; i++) {
    for (let a = 0; a < 3; a++) {
      const x = vertices[3 * i + a] - ca[a];
      for (let b = 0; b < 3; b++) S[a][b] += x * (target[3 * i + b] - cb[b]);
    }
  }
  const [[xx, xy, xz], [yx, yy, yz], [zx, zy, zz]] = S;
  const [w, x, y, z] = largestEigenvector4([
    [xx + yy + zz, yz - zy, zx - xz, xy - yx],
    [yz - zy, xx - yy - zz, xy + yx, zx + xz],
    [zx - xz, xy + yx, -xx + yy - zz, yz + zy],
    [xy - yx, zx + xz, yz + zy, -xx - yy + zz]]);
  const R = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]];
  const out = new Float64Array(vertices.length);
  for (let i = 0; i < n; i++) {
    const px = vertices[3 * i] - ca[0], py = vertices[3 * i + 1] - ca[1];
    const pz = vertices[3 * i + 2] - ca[2];
    for (let k = 0; k < 3; k++) {
      out[3 * i + k] = R[k][0] * px + R[k][1] * py + R[k][2] * pz + cb[k];
    }
  }
  return out;
}
