// Builds the viewer and the app into the Python package (service/static/app), where FastAPI serves them and the
// wheel carries them. Two bundles share the viewer: app.js (sign in, uploads, jobs, viewer) and viewer.js (the
// viewer alone: the offline file of `panogs export-html`, which inlines it); view.js, `panogs view`'s page, is the
// viewer as an ES module beside app.js, sharing its chunks (three.js, the photo view).
import { build } from "esbuild";
import { copyFileSync, mkdirSync, readdirSync, rmSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const out = join(here, "..", "service", "static", "app");
rmSync(out, { recursive: true, force: true });
mkdirSync(out, { recursive: true });

const common = {
  bundle: true,
  minify: true,
  target: ["es2020"],
  outdir: out,
  legalComments: "none",
  logLevel: "warning",
};
// app.js and view.js are ES modules split in chunks: the photo view (Spark, 3 MB with its WebAssembly) loads on
// demand.
await build({
  ...common,
  entryPoints: { app: join(here, "src", "app-main.js"), view: join(here, "src", "view-main.js") },
  format: "esm",
  splitting: true,
  chunkNames: "chunk-[hash]",
});
// viewer.js stays one classic script: the offline file of `panogs export-html` inlines it.
await build({ ...common, entryPoints: { viewer: join(here, "src", "viewer-standalone.js") }, format: "iife" });
for (const name of readdirSync(join(here, "public"))) {
  copyFileSync(join(here, "public", name), join(out, name));
}
console.log(`built ${readdirSync(out).sort().join(", ")} into ${out}`);
