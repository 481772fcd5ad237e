// Validate a glTF / GLB file with the Khronos glTF validator (npm: gltf-validator); prints its JSON report.
// node scripts/validate_gltf.mjs FILE.glb
import { readFileSync } from "node:fs";
import validator from "gltf-validator";

const path = process.argv[2];
const report = await validator.validateBytes(new Uint8Array(readFileSync(path)), { maxIssues: 100 });
console.log(JSON.stringify(report));
