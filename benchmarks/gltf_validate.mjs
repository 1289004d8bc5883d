// The Khronos glTF validator on GLB/glTF files: prints one JSON line per file with the issue counts and
// the first messages, and exits 1 if any file has an error or a warning.
//
// Run: node benchmarks/gltf_validate.mjs MODEL.glb [...]  with the npm package `gltf-validator` findable
// from here or from NODE_PATH's folder (e.g. `npm install gltf-validator` in /tmp/gv, then
// NODE_PATH=/tmp/gv/node_modules). Tests: tests/test_texture.py runs it where node and the package exist.
import { createRequire } from "node:module";
import { readFileSync } from "node:fs";
import path from "node:path";

const require = createRequire(import.meta.url);
let validator;
try {
  validator = require("gltf-validator");
} catch {
  const roots = (process.env.NODE_PATH || "").split(path.delimiter).filter(Boolean);
  for (const r of roots) {
    try { validator = require(path.join(r, "gltf-validator")); break; } catch { /* next */ }
  }
}
if (!validator) {
  console.error("gltf-validator not found (npm install gltf-validator; set NODE_PATH to its node_modules)");
  process.exit(2);
}

let bad = 0;
for (const file of process.argv.slice(2)) {
  const dir = path.dirname(file);
  const report = await validator.validateBytes(new Uint8Array(readFileSync(file)), {
    uri: path.basename(file),
    externalResourceFunction: (uri) =>
      Promise.resolve(new Uint8Array(readFileSync(path.join(dir, decodeURIComponent(uri))))),
  });
  const i = report.issues;
  const messages = i.messages.slice(0, 10).map((m) => `${m.severity} ${m.code} ${m.pointer ?? ""} ${m.message}`);
  console.log(JSON.stringify({ file, errors: i.numErrors, warnings: i.numWarnings, infos: i.numInfos,
                               hints: i.numHints, messages }));
  if (i.numErrors || i.numWarnings) bad += 1;
}
process.exit(bad ? 1 : 0);
