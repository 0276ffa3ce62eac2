// Copies the files the pages load from node_modules into service/static/vendor/<name>/
// (git-ignored; the service serves them at /static/vendor/): the three.js ES modules of the
// web page (its import map in service/static/index.html maps "three" and "three/addons/"
// there), and Swagger UI and ReDoc for the API documentation at /docs and /redoc
// (service/http/routes/docs.py), so that nothing is loaded from a CDN.
// Run by `npm ci --prefix web` (postinstall) and by `npm run build --prefix web`.
// A copied file may have URLs rewritten (REWRITES): ReDoc's sidebar credit loads its logo
// from cdn.redoc.ly, which the pages' Content-Security-Policy (this origin only) refuses; the
// copy loads web/redoc-logo-mini.svg from this service instead.
import { copyFileSync, mkdirSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const vendor = join(here, "..", "service", "static", "vendor");

// vendor directory -> [npm package, {file in the package: file in the directory}]
const PACKAGES = {
  three: ["three", {
    "build/three.module.js": "three.module.js",
    "build/three.core.js": "three.core.js",
    "examples/jsm/controls/OrbitControls.js": "addons/controls/OrbitControls.js",
    "examples/jsm/controls/TransformControls.js": "addons/controls/TransformControls.js",
    // The Blend panel plays the service's animated GLB (morph targets, an animation).
    "examples/jsm/loaders/GLTFLoader.js": "addons/loaders/GLTFLoader.js",
    "examples/jsm/utils/BufferGeometryUtils.js": "addons/utils/BufferGeometryUtils.js",
    "examples/jsm/utils/SkeletonUtils.js": "addons/utils/SkeletonUtils.js",
    "LICENSE": "LICENSE",
  }],
  "swagger-ui": ["swagger-ui-dist", {
    "swagger-ui-bundle.js": "swagger-ui-bundle.js",
    "swagger-ui.css": "swagger-ui.css",
    "LICENSE": "LICENSE",
    "NOTICE": "NOTICE",
  }],
  redoc: ["redoc", {
    "bundles/redoc.standalone.js": "redoc.standalone.js",
    "bundles/redoc.standalone.js.LICENSE.txt": "redoc.standalone.js.LICENSE.txt",
    "LICENSE": "LICENSE",
  }],
};

// vendor directory -> {copied file: [[text in it, replacement], ...]}
const REWRITES = {
  redoc: {
    "redoc.standalone.js": [["https://cdn.redoc.ly/redoc/logo-mini.svg",
      "/static/vendor/redoc/logo-mini.svg"]],
  },
};
// vendor directory -> {file of web/: file in the directory}
const LOCAL_FILES = { redoc: { "redoc-logo-mini.svg": "logo-mini.svg" } };

function rewrite(path, replacements) {
  let text = readFileSync(path, "utf8");
  for (const [from, to] of replacements) {
    if (!text.includes(from)) throw new Error(`build.mjs: ${path} no longer contains ${from}`);
    text = text.split(from).join(to);
  }
  writeFileSync(path, text);
}

for (const [name, [pkg, files]] of Object.entries(PACKAGES)) {
  const source = join(here, "node_modules", pkg);
  const out = join(vendor, name);
  const { version } = JSON.parse(readFileSync(join(source, "package.json"), "utf8"));
  rmSync(out, { recursive: true, force: true });
  for (const [from, to] of Object.entries(files)) {
    mkdirSync(dirname(join(out, to)), { recursive: true });
    copyFileSync(join(source, from), join(out, to));
  }
  for (const [file, replacements] of Object.entries(REWRITES[name] ?? {})) {
    rewrite(join(out, file), replacements);
  }
  for (const [from, to] of Object.entries(LOCAL_FILES[name] ?? {})) {
    copyFileSync(join(here, from), join(out, to));
    files[from] = to;
  }
  // Written last: the service checks for it to know the vendor files are complete.
  writeFileSync(join(out, "manifest.json"),
    JSON.stringify({ package: pkg, version, files: Object.values(files) }, null, 2) + "\n");
  console.log(`web: ${pkg} ${version} -> ${out}`);
}
