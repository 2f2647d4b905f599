// The photo view: the run's Gaussian scene (gaussians.ply, the fitted appearance) drawn as splats by Spark, in the
// points layer's three.js scene and camera, so that the points' class or instance colours and the lit instances
// (selection, query hits) draw over it. Loaded on demand by the app (a chunk of its own): Spark brings 3 MB of
// code and a WebAssembly module, which the points modes, `panogs view` and the offline file never need.
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

// layer: a PointsLayer; bytes: the PLY file's bytes. Returns { mesh, dispose() } once the splats are ready.
export async function addSplats(layer, bytes) {
  const spark = new SparkRenderer({ renderer: layer.renderer });
  const mesh = new SplatMesh({ fileBytes: bytes, fileType: "ply" });
  await mesh.initialized;
  mesh.renderOrder = 0; // before the overlay points (renderOrder 1)
  layer.three.add(spark, mesh);
  return {
    mesh,
    setVisible(visible) {
      mesh.visible = visible;
      spark.visible = visible;
    },
    dispose() {
      layer.three.remove(spark, mesh);
      mesh.dispose();
      spark.dispose?.();
    },
  };
}
