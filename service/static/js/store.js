// The page's state, declared once, and the views that draw it. `store.set(patch)` assigns
// fields and then calls, once, every view subscribed to a field that changed (identity:
// a field changed in place is announced with `store.changed(key)`). The state is sealed: a
// field that is not declared here cannot be added on the fly, and setting one throws.

/** Every field of the page's state, with its value before a mesh is opened. */
export const INITIAL_STATE = {
  // the mesh on screen
  name: null,
  source: null,          // "sample" | "upload" | "reconstruction"
  vertices: null,        // Float64Array(3n): what is shown
  faces: null,           // Uint32Array(3m)
  topo: null,            // mesh.topology(): edges and their faces
  meanEdge: null,
  boundaryEdges: 0,
  closed: false,         // no boundary edge: no flat layout, selection of facing vertices
  up: "+y",
  upSource: "guess",     // "guess" | "sample" | "user"
  // the Mesh panel's integrability report
  reference: null,       // forms of the shape as loaded: the distortion reference
  forms: null,           // forms document of the loaded mesh (or of the uploaded forms)
  integrability: null,
  analysisError: null,   // api.describe() of the refusal, when there is no report
  defectPart: "vertex_defect",
  // the view's colours
  colorMode: "plain",    // "plain" | "defect" | "distortion" | "checker"
  distortion: null,      // mesh.distortion() of the shown shape against `reference`
  distortionKind: "length",
  // Flatten and Rebuild
  flat: null,            // {uv, flipped, report, texcoords}
  reconstruction: null,  // {input, report, refinement, integrability, alignTo, refined, linear, showing}
  // Deform
  selection: [],
  handles: [],           // {id, vertices, start, center, pivot, color, rotationFaces}
  active: null,
  rest: null,            // deformation rest shape (Float64Array)
  deformed: false,
  orthonormalize: false,
  refineDrags: true,     // progressive drags: the linear shape at once, settling to the refined
  transport: null,       // the open deformation transport (deform.js)
  transportKey: null,    // what it was opened for (drag-loop.js)
  solves: 0,
  lastSolveMs: null,
  lastApplyMs: null,
  undo: [],
  redo: [],
  inViewBefore: false,   // the shape was on screen when the step began (history.js)
  // Blend
  blendShapes: [],       // {name, vertices: Float64Array(3n)}: 2 to 4 shapes of the mesh
  blendReport: null,     // {rows, length, angle, warnings}: the worst row's form errors, the rows' warnings
  blendFrame: -1,        // frames drawn of the playing sequence (-1: a single blend shown)
  blendTime: 0,          // the animation's time (s)
  blendPlaying: false,
  // the page
  sizeLimits: null,      // GET /v1/me's size_limits: the most faces, bytes, per operation
  tab: "mesh",
  errors: [],            // api.describe() of every error shown
};

export class Store {
  constructor(initial) {
    this.state = Object.seal({ ...initial });
    this.views = [];
  }

  /** Assign the fields of `patch`, then draw the views of those that changed. */
  set(patch) {
    const changed = [];
    for (const [key, value] of Object.entries(patch)) {
      if (!(key in this.state)) throw new TypeError(`the page's state has no field "${key}"`);
      if (this.state[key] !== value) {
        this.state[key] = value;
        changed.push(key);
      }
    }
    if (changed.length) this.changed(...changed);
  }

  /** Draw the views of `keys` (after a field was changed in place). */
  changed(...keys) {
    for (const view of [...this.views]) {
      if (keys.some((key) => view.keys.has(key))) view.draw(this.state);
    }
  }

  /** Call `draw(state)` whenever one of `keys` changes, and once now; returns the
   * unsubscribe function. */
  subscribe(keys, draw) {
    for (const key of keys) {
      if (!(key in this.state)) throw new TypeError(`the page's state has no field "${key}"`);
    }
    const view = { keys: new Set(keys), draw };
    this.views.push(view);
    draw(this.state);
    return () => { this.views = this.views.filter((v) => v !== view); };
  }
}

export const store = new Store(INITIAL_STATE);
export const state = store.state;
