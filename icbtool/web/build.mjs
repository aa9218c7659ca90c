// Bundle the browser client (`make web`, part of `make install`): src/app.js with three.js,
// fzstd and onnxruntime-web (from node_modules, versions pinned by package-lock.json) into
// bundle/app.js, shaders inlined as text, plus onnxruntime-web's WebAssembly files next to it.
// Nothing is fetched from a CDN at run time: the server serves bundle/ itself.
import {build} from "esbuild";
import {copyFileSync, mkdirSync} from "node:fs";
import {dirname, join} from "node:path";
import {fileURLToPath} from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const out = join(here, "bundle");
mkdirSync(out, {recursive: true});
await build({
  entryPoints: [join(here, "src", "app.js")],
  bundle: true,
  format: "esm",
  target: "es2022",
  minify: true,
  sourcemap: false,
  legalComments: "linked",
  outfile: join(out, "app.js"),
  loader: {".vert": "text", ".frag": "text"},
  logLevel: "warning",
});
const ort = join(here, "..", "..", "node_modules", "onnxruntime-web", "dist");
for (const f of ["ort-wasm-simd-threaded.wasm", "ort-wasm-simd-threaded.mjs"]) {
  copyFileSync(join(ort, f), join(out, f));
}
console.log(`bundled the web client into ${out}`);
