// Validate one glTF 2.0 asset with the official Khronos glTF-Validator (npm `gltf-validator`).
//
// Usage: node validate.mjs [--format glb|gltf] [--max-issues N] <path | ->
//   `-` (or no path) reads the asset from standard input.
// Prints the validator's report as JSON on stdout and exits 0 whenever a report was produced,
// whatever issues it lists; the caller decides what counts as a failure (see
// tests/gltf_validator.py). Exits 2 on bad arguments and 3 when the validator rejects the input
// outright (e.g. it cannot detect the format).
import { readFileSync } from "node:fs";
import validator from "gltf-validator";

function usage(message) {
  process.stderr.write(`${message}\nusage: node validate.mjs [--format glb|gltf] [--max-issues N] <path|->\n`);
  process.exit(2);
}

const args = process.argv.slice(2);
let format;
let maxIssues = 0; // 0 = unlimited
let source = "-";
for (let i = 0; i < args.length; i += 1) {
  const arg = args[i];
  if (arg === "--format") {
    format = args[++i];
    if (format !== "glb" && format !== "gltf") usage(`bad --format: ${format}`);
  } else if (arg === "--max-issues") {
    maxIssues = Number.parseInt(args[++i], 10);
    if (!Number.isInteger(maxIssues) || maxIssues < 0) usage("bad --max-issues");
  } else if (arg.startsWith("--")) {
    usage(`unknown option: ${arg}`);
  } else {
    source = arg;
  }
}

const data = new Uint8Array(readFileSync(source === "-" ? 0 : source));
const options = {
  uri: source === "-" ? `stdin.${format ?? "glb"}` : source,
  maxIssues,
  writeTimestamp: false,
  // Only embedded (data: URI / GLB BIN chunk) buffers are expected; refuse anything external.
  externalResourceFunction: (uri) => Promise.reject(new Error(`external resource not allowed: ${uri}`)),
};
if (format) options.format = format;

try {
  const report = await validator.validateBytes(data, options);
  process.stdout.write(`${JSON.stringify(report)}\n`);
} catch (error) {
  process.stderr.write(`gltf-validator rejected the input: ${error}\n`);
  process.exit(3);
}
