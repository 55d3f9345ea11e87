// Validates .glb files with the Khronos glTF validator (npm package `gltf-validator`, pinned in package.json).
//
// Usage: node tests/gltf/validate.mjs FILE.glb [FILE.glb ...]
// Prints every issue the validator reports and a summary line per file; exits 1 if any file has an error or a
// warning (infos and hints are printed but allowed), 2 on bad usage or an unreadable file.
// Install once with `npm ci` in tests/gltf.

import fs from 'node:fs';
import path from 'node:path';
import validator from 'gltf-validator';

const SEVERITY = ['error', 'warning', 'info', 'hint'];

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error('usage: node validate.mjs FILE.glb [FILE.glb ...]');
  process.exit(2);
}

// The whole file, read a GiB at a time: readFileSync stops at 2 GiB, a typed array holds up to 4 GiB (all a GLB
// can be: its lengths are u32).
function readAll(file) {
  const fd = fs.openSync(file, 'r');
  try {
    const size = fs.fstatSync(fd).size;
    const bytes = new Uint8Array(size);
    for (let at = 0; at < size; ) {
      const n = fs.readSync(fd, bytes, at, Math.min(size - at, 1 << 30), at);
      if (n === 0) throw new Error(`the file ended at ${at} of ${size} bytes`);
      at += n;
    }
    return bytes;
  } finally {
    fs.closeSync(fd);
  }
}

let failed = false;
for (const file of files) {
  let bytes;
  try {
    bytes = readAll(file);
  } catch (e) {
    console.error(`${file}: cannot read: ${e.message}`);
    process.exit(2);
  }
  let report;
  try {
    report = await validator.validateBytes(bytes, { maxIssues: 0, uri: path.basename(file) });
  } catch (e) {
    console.error(`${file}: validator failed: ${e}`);
    failed = true;
    continue;
  }
  const issues = report.issues;
  for (const m of issues.messages) {
    const where = m.pointer ?? (m.offset !== undefined ? `@${m.offset}` : '');
    console.log(`${file}: ${SEVERITY[m.severity] ?? m.severity}: ${m.code} ${where}: ${m.message}`);
  }
  const info = report.info ?? {};
  console.log(
    `${file}: ${issues.numErrors} errors, ${issues.numWarnings} warnings, ${issues.numInfos} infos, ` +
      `${issues.numHints} hints (validator ${report.validatorVersion}; ${info.drawCallCount ?? 0} draw calls, ` +
      `${info.totalVertexCount ?? 0} vertices, ${info.totalTriangleCount ?? 0} triangles)`,
  );
  if (issues.numErrors > 0 || issues.numWarnings > 0) failed = true;
}
process.exit(failed ? 1 : 0);
