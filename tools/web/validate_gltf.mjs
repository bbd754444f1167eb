// Runs the Khronos glTF-Validator (npm package gltf-validator) on one .glb/.gltf file and prints
// its report as JSON on stdout. Used by morpheus_core/export/gltf_validator.py.
//
//   node tools/web/validate_gltf.mjs FILE [--modules DIR]
//
// DIR is the folder holding node_modules/gltf-validator (default: this script's folder), so the
// Python side can point at another install without moving this script. Exit status 0 means "a
// report was printed" (the asset may still have errors); 2 means bad arguments or an unreadable
// file; 3 means the validator itself failed. Diagnostics go to stderr only, so stdout is pure JSON.

import { readFile } from 'node:fs/promises';
import { createRequire } from 'node:module';
import path from 'node:path';
import { fileURLToPath } from 'node:url';

function usage(message) {
  process.stderr.write(`validate_gltf.mjs: ${message}\nusage: node validate_gltf.mjs FILE [--modules DIR]\n`);
  process.exit(2);
}

const args = process.argv.slice(2);
let file = null;
let modulesDir = path.dirname(fileURLToPath(import.meta.url));
for (let i = 0; i < args.length; i++) {
  if (args[i] === '--modules') {
    if (i + 1 >= args.length) usage('--modules needs a folder');
    modulesDir = path.resolve(args[++i]);
  } else if (file === null) {
    file = path.resolve(args[i]);
  } else {
    usage(`unexpected argument ${args[i]}`);
  }
}
if (file === null) usage('no file given');

// Resolve the validator from DIR, not from wherever this script lives.
const requireFrom = createRequire(path.join(modulesDir, 'package.json'));
let validator;
try {
  validator = requireFrom('gltf-validator');
} catch (err) {
  process.stderr.write(`validate_gltf.mjs: cannot load gltf-validator from ${modulesDir}: ${err.message}\n`);
  process.exit(3);
}

let data;
try {
  data = await readFile(file);
} catch (err) {
  usage(`cannot read ${file}: ${err.message}`);
}

// External buffers/images of a .gltf are read relative to it; a GLB normally has none.
const baseDir = path.dirname(file);
const loadExternal = async (uri) => new Uint8Array(await readFile(path.join(baseDir, decodeURIComponent(uri))));

try {
  const report = await validator.validateBytes(new Uint8Array(data.buffer, data.byteOffset, data.byteLength), {
    uri: path.basename(file),
    externalResourceFunction: loadExternal,
    writeTimestamp: false,
    maxIssues: 0, // unlimited: the caller counts and filters
  });
  process.stdout.write(JSON.stringify(report));
  process.stdout.write('\n');
} catch (err) {
  process.stderr.write(`validate_gltf.mjs: validator failed on ${file}: ${err && err.message ? err.message : err}\n`);
  process.exit(3);
}
