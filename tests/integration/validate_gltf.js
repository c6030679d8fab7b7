// Validates GLB files with Khronos' glTF validator (npm `gltf-validator`, installed by
// install-node-tools.sh) and prints one JSON line per file: its name, the issue counts by
// severity and the first issues. Usage: node validate_gltf.js <node-tools prefix> <file.glb>...
'use strict';
const fs = require('fs');
const path = require('path');

const [prefix, ...files] = process.argv.slice(2);
const validator = require(path.join(path.resolve(prefix), 'node_modules', 'gltf-validator'));

(async () => {
  for (const file of files) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
      uri: path.basename(file),
      maxIssues: 20,
      // Everything the asset needs is inside the GLB: any external reference is an error.
      externalResourceFunction: (uri) => Promise.reject(new Error('external resource ' + uri)),
    });
    const issues = report.issues;
    console.log(JSON.stringify({
      file,
      errors: issues.numErrors,
      warnings: issues.numWarnings,
      infos: issues.numInfos,
      hints: issues.numHints,
      messages: issues.messages.slice(0, 10).map((m) => `${m.severity} ${m.code} ${m.pointer || ''} ${m.message}`),
      validator: report.validatorVersion,
    }));
  }
})().catch((e) => {
  console.error(e);
  process.exit(1);
});
