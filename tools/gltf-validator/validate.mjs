// Validate one glTF / GLB file with the Khronos glTF validator and print its report
// (JSON) on stdout: `node validate.mjs FILE`. Exit 0 when the validator ran (read
// the report's issues.numErrors), 2 when it could not run. Used by
// tests/gltf_validator.py; install the validator first: `npm ci` in this folder.
import { readFile } from "node:fs/promises";
import { basename } from "node:path";
import validator from "gltf-validator";

const file = process.argv[2];
if (!file) {
  console.error("usage: node validate.mjs FILE.glb");
  process.exit(2);
}
try {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(bytes, {
    uri: basename(file),
    maxIssues: 0, // 0: no limit, every issue is counted and listed
  });
  process.stdout.write(JSON.stringify(report) + "\n");
} catch (err) {
  console.error(`gltf-validator could not validate ${file}: ${err}`);
  process.exit(2);
}
