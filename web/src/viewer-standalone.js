// The offline file's viewer (`panogs export-html` inlines this one classic script): no photo view, so Spark's code
// and WebAssembly stay out of the file.
import { startViewer } from "./viewer-main.js";

startViewer(null);
