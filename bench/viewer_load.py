"""Viewer load time to interactive in headless Chromium, for 100k and 1M primitives.

For each size: a synthetic run folder (random primitives in a 10 m room, 200 instances over 20 classes; no pipeline,
only the files the viewer reads), served by ``panogs view``'s server on 127.0.0.1, opened by Debian's chromium
(Playwright, WebGL in software by SwiftShader: no GPU). Measured, median of ``--repeats`` page loads:

- ``build``: the server building the binary scene from the run folder (once, at ``panogs view`` start);
- ``ready``: navigation start to the viewer ready (scene fetched with progress, parsed, buffers built, legend and
  lists filled, controls live);
- ``first frame``: drawing the first frame after that (the buffers go to the GPU; forced to finish by reading a
  pixel back);
- ``interactive``: ready + first frame, the time until the scene is on screen and answers the mouse;
- ``frame``: one more frame (what orbiting costs per frame);
- ``mode switch``: recolouring every primitive (semantic -> instance) and drawing.

    .venv/bin/python bench/viewer_load.py [--sizes 100000 1000000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from panogs_core.gaussians.config import GaussianScene
from panogs_core.gaussians.ply import write_gaussian_ply
from panogs_core.io.run_folder import GAUSSIANS_PLY
from service.viewer.local import RunViewer, serve

CHROMIUM = os.environ.get("PANOGS_TEST_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
NUM_CLASSES = 20
NUM_INSTANCES = 200


def synthetic_run(out: Path, n: int, seed: int = 0) -> None:
    """A run folder of ``n`` primitives: the files the viewer and the query code read."""
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True)
    points = rng.uniform(0, 10, (n, 3)).astype(np.float32)
    instance = rng.integers(0, NUM_INSTANCES, n).astype(np.int32)
    semantic = (instance % NUM_CLASSES).astype(np.int32)
    log_scale = np.full((n, 3), np.log(0.02), np.float32)
    dc = rng.normal(0, 1, (n, 3)).astype(np.float32)
    quats = np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))
    opacity = np.zeros(n, np.float32)
    gaussians = GaussianScene(
        means=points, sh=dc[:, None, :], opacity_logits=opacity, log_scales=log_scale, quats=quats, fitted=True
    )
    write_gaussian_ply(GAUSSIANS_PLY.path(out), gaussians, np.zeros((n, 3), np.float32), semantic, instance)
    dim = 8
    embeddings = np.eye(NUM_CLASSES, dim, dtype=np.float32) + 0.01
    rows = []
    for k in range(NUM_INSTANCES):
        mine = points[instance == k]
        rows.append({"id": k, "class_index": k % NUM_CLASSES, "class_name": f"class{k % NUM_CLASSES}",
                     "kind": "thing", "score": 0.9, "num_points": len(mine), "centroid": mine.mean(0).tolist(),
                     "bbox_min": mine.min(0).tolist(), "bbox_max": mine.max(0).tolist()})  # fmt: skip
    (out / "instances.json").write_text(json.dumps(rows))
    np.save(out / "instance_features.npy", embeddings[np.arange(NUM_INSTANCES) % NUM_CLASSES])
    np.save(out / "vocabulary.npy", embeddings)
    classes = [{"name": f"class{k}", "kind": "thing"} for k in range(NUM_CLASSES)]
    doc = {"classes": classes, "embeddings": "vocabulary.npy", "space": "bench"}
    (out / "vocabulary.json").write_text(json.dumps(doc))


def start_server(viewer: RunViewer) -> str:
    """Serve ``viewer`` on a free port in a daemon thread; its URL."""
    ready = threading.Event()
    urls: list[str] = []

    def on_ready(url: str) -> None:
        urls.append(url)
        ready.set()

    threading.Thread(target=serve, args=(viewer, 0, on_ready), daemon=True).start()
    ready.wait(10)
    return urls[0]


def measure(browser: object, url: str, repeats: int) -> dict[str, float]:
    """Median milliseconds of each phase over ``repeats`` fresh page loads."""
    phases: dict[str, list[float]] = {"ready": [], "first_frame": [], "interactive": [], "frame": [], "mode_switch": []}
    for _ in range(repeats):
        page = browser.new_page(viewport={"width": 1280, "height": 800})  # type: ignore[attr-defined]
        page.goto(url)
        page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=300_000)
        ready = page.evaluate("window.__panogs.readyAt")
        timings = page.evaluate(
            """() => {
              const v = window.__panogs.viewer;
              const gl = v.renderer.getContext();
              const px = new Uint8Array(4);
              const draw = () => { v.renderNow(); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px); };
              let t = performance.now(); draw(); const first = performance.now() - t;
              t = performance.now(); draw(); const frame = performance.now() - t;
              t = performance.now(); v.setMode("instance"); draw(); const mode = performance.now() - t;
              return [first, frame, mode];
            }"""
        )
        phases["ready"].append(ready)
        phases["first_frame"].append(timings[0])
        phases["interactive"].append(ready + timings[0])
        phases["frame"].append(timings[1])
        phases["mode_switch"].append(timings[2])
        page.close()
    return {k: statistics.median(v) for k, v in phases.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    print(f"{'primitives':>11} {'scene MB':>9} {'build s':>8} {'ready ms':>9} {'1st frame ms':>13} "
          f"{'interactive ms':>15} {'frame ms':>9} {'mode switch ms':>15}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        for n in args.sizes:
            folder = Path(tmp) / f"run-{n}"
            synthetic_run(folder, n)
            start = time.perf_counter()
            viewer = RunViewer(folder)
            build_s = time.perf_counter() - start
            url = start_server(viewer)
            m = measure(browser, url, args.repeats)
            print(f"{n:>11,} {len(viewer.scene.data) / 1e6:>9.1f} {build_s:>8.2f} {m['ready']:>9.0f} "
                  f"{m['first_frame']:>13.0f} {m['interactive']:>15.0f} {m['frame']:>9.0f} "
                  f"{m['mode_switch']:>15.0f}", flush=True)  # fmt: skip
        browser.close()


if __name__ == "__main__":
    main()
