// Builds the viewer and the app into the Python package (service/static/app), where FastAPI serves them and the
// wheel carries them. Two bundles share the viewer: app.js (sign in, uploads, jobs, viewer) and viewer.js (the
// viewer alone: `panogs view` and the offline file of `panogs export-html`, which inlines it).
import { build } from "esbuild";
import { copyFileSync, mkdirSync, readdirSync, rmSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const out = join(here, "..", "service", "static", "app");
rmSync(out, { recursive: true, force: true });
mkdirSync(out, { recursive: true });

await build({
  entryPoints: { app: join(here, "src", "app-main.js"), viewer: join(here, "src", "viewer-main.js") },
  bundle: true,
  minify: true,
  format: "iife",
  target: ["es2020"],
  outdir: out,
  legalComments: "none",
  logLevel: "warning",
});
for (const name of readdirSync(join(here, "public"))) {
  copyFileSync(join(here, "public", name), join(out, name));
}
console.log(`built ${readdirSync(out).sort().join(", ")} into ${out}`);
