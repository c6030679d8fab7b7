// Validates GLB files with Khronos' glTF validator (npm `gltf-validator`, installed by
// install-node-tools.sh) and prints one JSON line per file: its name, the issue counts by
// severity and the first issues. Usage: node validate_gltf.js <node-tools prefix> <file.glb>...
//
// The validator does not know EXT_meshopt_compression (an info, UNSUPPORTED_EXTENSION): it checks
// such a file's JSON and layout but cannot read its vertex and index data. So each GLB using it is
// also decoded here with meshoptimizer's JavaScript decoder (npm `meshoptimizer`, the one three.js
// ships) into a plain GLB (every view's bytes in one BIN chunk, EXT_meshopt_compression dropped,
// KHR_mesh_quantization kept) and that one validated too, with its data: one more line, its file
// "<file>#decoded".
'use strict';
const fs = require('fs');
const path = require('path');

const [prefix, ...files] = process.argv.slice(2);
const modules = path.join(path.resolve(prefix), 'node_modules');
const validator = require(path.join(modules, 'gltf-validator'));
const { MeshoptDecoder } = loadDecoder();

function loadDecoder() {
  const decoder = require(path.join(modules, 'meshoptimizer', 'meshopt_decoder.js'));
  return { MeshoptDecoder: decoder.MeshoptDecoder || decoder };
}

const pad4 = (n) => (n + 3) & ~3;

/// The GLB `bytes` with its EXT_meshopt_compression views decoded, or null when it has none.
function decodeMeshopt(bytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const jsonLength = view.getUint32(12, true);
  const gltf = JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLength)));
  if (!(gltf.extensionsUsed || []).includes('EXT_meshopt_compression')) {
    return null;
  }
  const binStart = 20 + jsonLength + 8;
  const bin = bytes.subarray(binStart, binStart + view.getUint32(20 + jsonLength, true));
  const parts = [];
  let offset = 0;
  for (const bufferView of gltf.bufferViews) {
    const ext = (bufferView.extensions || {}).EXT_meshopt_compression;
    let data;
    if (ext) {
      if (ext.buffer !== 0) throw new Error('compressed data outside the BIN chunk');
      data = new Uint8Array(ext.count * ext.byteStride);
      const source = bin.subarray(ext.byteOffset || 0, (ext.byteOffset || 0) + ext.byteLength);
      MeshoptDecoder.decodeGltfBuffer(data, ext.count, ext.byteStride, source, ext.mode,
                                      ext.filter || 'NONE');
      if (data.length !== bufferView.byteLength) throw new Error('decoded length differs');
      delete bufferView.extensions.EXT_meshopt_compression;
      if (Object.keys(bufferView.extensions).length === 0) delete bufferView.extensions;
    } else {
      if (bufferView.buffer !== 0) throw new Error('plain view outside the BIN chunk');
      data = bin.subarray(bufferView.byteOffset || 0,
                          (bufferView.byteOffset || 0) + bufferView.byteLength);
    }
    bufferView.buffer = 0;
    bufferView.byteOffset = offset;
    parts.push({ offset, data });
    offset = pad4(offset + data.length);
  }
  gltf.buffers = [{ byteLength: offset }];
  for (const list of ['extensionsUsed', 'extensionsRequired']) {
    if (gltf[list]) {
      gltf[list] = gltf[list].filter((e) => e !== 'EXT_meshopt_compression');
      if (gltf[list].length === 0) delete gltf[list];
    }
  }
  let text = JSON.stringify(gltf);
  text += ' '.repeat(pad4(text.length) - text.length);
  const json = new TextEncoder().encode(text);
  const total = 12 + 8 + json.length + 8 + offset;
  const out = new Uint8Array(total);
  const o = new DataView(out.buffer);
  o.setUint32(0, 0x46546c67, true);
  o.setUint32(4, 2, true);
  o.setUint32(8, total, true);
  o.setUint32(12, json.length, true);
  o.setUint32(16, 0x4e4f534a, true);
  out.set(json, 20);
  o.setUint32(20 + json.length, offset, true);
  o.setUint32(24 + json.length, 0x004e4942, true);
  for (const part of parts) {
    out.set(part.data, 28 + json.length + part.offset);
  }
  return out;
}

(async () => {
  await MeshoptDecoder.ready;
  for (const file of files) {
    const bytes = new Uint8Array(fs.readFileSync(file));
    const decoded = decodeMeshopt(bytes);
    await report(file, bytes);
    if (decoded) {
      await report(file + '#decoded', decoded);
    }
  }
})().catch((e) => {
  console.error(e);
  process.exit(1);
});

async function report(file, bytes) {
  const result = await validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 20,
    // Everything the asset needs is inside the GLB: any external reference is an error.
    externalResourceFunction: (uri) => Promise.reject(new Error('external resource ' + uri)),
  });
  const issues = result.issues;
  console.log(JSON.stringify({
    file,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    hints: issues.numHints,
    messages: issues.messages.slice(0, 10).map((m) => `${m.severity} ${m.code} ${m.pointer || ''} ${m.message}`),
    validator: result.validatorVersion,
  }));
}
