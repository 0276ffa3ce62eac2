// Copies the three.js ES modules the page loads from node_modules into
// service/static/vendor/three/ (git-ignored; the service serves it at /static/vendor/three/).
// Run by `npm ci --prefix web` (postinstall) and by `npm run build --prefix web`.
// The page's import map (service/static/index.html) maps "three" and "three/addons/" there.
import { copyFileSync, mkdirSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const three = join(here, "node_modules", "three");
const out = join(here, "..", "service", "static", "vendor", "three");

const FILES = {
  "build/three.module.js": "three.module.js",
  "build/three.core.js": "three.core.js",
  "examples/jsm/controls/OrbitControls.js": "addons/controls/OrbitControls.js",
  "examples/jsm/controls/TransformControls.js": "addons/controls/TransformControls.js",
  "LICENSE": "LICENSE",
};

const { version } = JSON.parse(readFileSync(join(three, "package.json"), "utf8"));
rmSync(out, { recursive: true, force: true });
for (const [from, to] of Object.entries(FILES)) {
  mkdirSync(dirname(join(out, to)), { recursive: true });
  copyFileSync(join(three, from), join(out, to));
}
// Written last: the service checks for it to know the vendor files are complete.
writeFileSync(join(out, "manifest.json"),
  JSON.stringify({ package: "three", version, files: Object.values(FILES) }, null, 2) + "\n");
console.log(`web: three ${version} -> ${out}`);
