// Validate glTF/GLB files with the Khronos glTF validator (npm gltf-validator, installed by scripts/setup.sh
// into .tools/node). Prints one JSON report per file; exit code 1 when any file has errors.
//   node scripts/validate_gltf.mjs FILE.glb [...]
import fs from "node:fs";
import path from "node:path";
import { createRequire } from "node:module";
import { fileURLToPath } from "node:url";

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..");
const modules = process.env.ELICIT_NODE_MODULES || path.join(root, ".tools", "node", "node_modules");
const validator = createRequire(path.join(modules, "noop.js"))("gltf-validator");
let failed = false;
for (const file of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), { maxIssues: 100 });
  const issues = report.issues;
  failed ||= issues.numErrors > 0;
  console.log(JSON.stringify({
    file,
    validator: report.validatorVersion,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    messages: issues.messages.map((m) => `${m.severity === 0 ? "error" : m.severity === 1 ? "warning" : "info"} ${m.code} ${m.pointer ?? ""}: ${m.message}`),
  }));
}
process.exit(failed ? 1 : 0);
