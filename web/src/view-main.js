// `panogs view RUN_DIR`'s viewer: an ES module, so the photo view (Spark, a chunk of its own) loads on demand from
// the local server, with the run's gaussians.ply beside the scene.
import { startViewer } from "./viewer-main.js";

startViewer({
  load: () => import("./viewer/photo.js"),
  bytes: async () => {
    const response = await fetch("gaussians.ply");
    if (!response.ok) throw new Error(`gaussians.ply: ${response.status}`);
    return new Uint8Array(await response.arrayBuffer());
  },
});
