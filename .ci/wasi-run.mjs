// Runs a wasm32-wasip1 test binary under node's WASI (cargo's runner for that target in .ci/cross-determinism).
import { readFile } from 'node:fs/promises';
import { WASI } from 'node:wasi';
import process from 'node:process';

const wasi = new WASI({
  version: 'preview1',
  args: process.argv.slice(2),
  env: process.env,
  preopens: {},
  returnOnExit: true,
});
const module = await WebAssembly.compile(await readFile(process.argv[2]));
const instance = await WebAssembly.instantiate(module, wasi.getImportObject());
// Let node exit on its own with the program's status.
process.exitCode = wasi.start(instance);
