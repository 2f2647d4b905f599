"""Speed benchmark: per-stage wall time and peak RSS of the whole pipeline on the large synthetic preset,
and, in the same run, the I/O floor (the time to read every input file of the bundle once).

Usage:
    python bench/speed.py [--preset large] [--seed 0] [--work bench/results/speed] [--set KEY=VALUE ...]
    python bench/speed.py --preset scannet-size --set appearance.enabled=false   # the ScanNet-size case

``scannet-size`` is the ``scan`` room at the held-out real capture's size (about 80k primitives, 100 key frames,
512-d features at 160x120, 640x480 depth and masks; docs/synthetic.md); its time to labels is measured without
the appearance fit. ``--set`` goes to ``panogs run`` as is.

The scene is generated once and reused. The pipeline runs in a child process (``panogs run --no-resume``) so
its peak RSS is its own; the numbers come from that run's report.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def io_floor(bundle: Path) -> tuple[float, int, int]:
    """Seconds to read (decode) every referenced file once, the number of files and bytes."""
    manifest = json.loads((bundle / "scene.json").read_text())
    t0 = time.perf_counter()
    files = 0
    nbytes = 0
    for frame in manifest["frames"]:
        for key in ("color", "depth", "masks"):
            if frame.get(key):
                img = cv2.imread(str(bundle / frame[key]), cv2.IMREAD_UNCHANGED)
                nbytes += img.nbytes
                files += 1
        if frame.get("features"):
            arr = np.load(bundle / frame["features"], allow_pickle=False)
            nbytes += arr.nbytes
            files += 1
    geometry = bundle / "geometry.ply"
    if geometry.is_file():
        nbytes += len(geometry.read_bytes())
        files += 1
    return time.perf_counter() - t0, files, nbytes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="large")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default="bench/results/speed")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()

    work = Path(args.work)
    bundle = work / f"{args.preset}-{args.seed}"
    if not (bundle / "scene.json").is_file():
        from panogs_core.synthetic import make_scene

        t0 = time.perf_counter()
        make_scene(bundle, preset=args.preset, difficulty="default", seed=args.seed)
        print(f"generated {bundle} in {time.perf_counter() - t0:.1f} s")

    floor_s, files, nbytes = io_floor(bundle)
    out = work / f"run-{args.preset}-{args.seed}"
    t0 = time.perf_counter()
    subprocess.run(
        [
            sys.executable,
            "-m",
            "panogs_core.cli",
            "run",
            str(bundle),
            "--out",
            str(out),
            "--no-resume",
            "--quiet",
            *[arg for item in args.overrides for arg in ("--set", item)],
        ],
        check=True,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
    )
    wall = time.perf_counter() - t0
    report = json.loads((out / "report.json").read_text())

    print(
        f"\nscene {report['scene']}: {report['num_primitives']} primitives, {report['num_frames']} frames, "
        f"{report['feature_dim']}-d features, {report['num_instances']} instances"
    )
    print(f"I/O floor: {floor_s:.1f} s to read {files} files ({nbytes / 2**20:.0f} MiB decoded)\n")
    print("| stage | wall s | peak RSS MB |")
    print("|---|---:|---:|")
    for st in report["stages"]:
        beside = f" (beside {st['beside']})" if "beside" in st else ""  # its time overlaps that stage's
        print(f"| {st['stage']}{beside} | {st['wall_s']:.2f} | {st['peak_rss_mb']:.0f} |")
    if "results_wall_s" in report:
        print(f"| to the results (in-process) | {report['results_wall_s']:.1f} | |")
    print(f"| **total (in-process)** | **{report['total_wall_s']:.1f}** | **{report['peak_rss_mb']:.0f}** |")
    print(f"\nwhole command incl. interpreter start and imports: {wall:.1f} s")


if __name__ == "__main__":
    main()
