// Validate glTF/GLB files with the Khronos glTF-Validator (npm package gltf-validator).
// usage: node gltf_validate.cjs FILE...  -> one JSON line per file: {file, errors, warnings, infos, hints, messages}
// Exit code 2 when the validator package cannot be loaded.
const fs = require("fs");
const path = require("path");
let validator;
try {
  validator = require(path.resolve(__dirname, "../../node_modules/gltf-validator"));
} catch (e) {
  console.error("gltf-validator not found in node_modules (run `npm ci`): " + e.message);
  process.exit(2);
}
(async () => {
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
      uri: path.basename(file),
      maxIssues: 0,
      writeTimestamp: false,
      externalResourceFunction: (uri) => Promise.resolve(new Uint8Array(fs.readFileSync(path.resolve(path.dirname(file), decodeURIComponent(uri))))),
    });
    const i = report.issues;
    console.log(JSON.stringify({
      file, validator: report.validatorVersion, errors: i.numErrors, warnings: i.numWarnings, infos: i.numInfos,
      hints: i.numHints, messages: i.messages.map((m) => `${m.severity}:${m.code}:${m.pointer || ""}:${m.message}`),
      extensions: report.info && report.info.extensionsUsed,
    }));
  }
})().catch((e) => { console.error(String(e)); process.exit(1); });
