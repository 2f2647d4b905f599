"""ScanNet-like round trip: a synthetic scene written out as a ScanNet export, imported and run with the real CLI.

Usage:
    python bench/scannet_like.py [--preset tiny] [--difficulty default] [--seed 0] [--work bench/results/scannet_like]
                                 [--invalid-fraction 0.03] [--set SECTION.KEY=VALUE ...] [--json FILE]

The synthetic scene (CLIP space, no geometry: its ground truth carries points) is written in the layout a real
ScanNet user has after SensReader, with the quirks of real exports:

- ``color/<i>.jpg`` upscaled to 1296x968, ``depth/<i>.png`` uint16 millimetres at the depth camera size,
  ``pose/<i>.txt`` 4x4 text with about 3 % of the poses ``-inf`` (lost tracking), ``intrinsic/intrinsic_depth.txt``
  (and ``intrinsic_color.txt``) 4x4, ``features/<i>.npy`` (H/4, W/4, 512) float16, ``masks/<i>.png`` 16-bit ids;
- frame indices every 10th frame with random gaps (exports keep every n-th frame, some are dropped);
- the ground truth as ``gt.npz`` (semantic, instance, points) next to the export.

Then ``panogs import scannet SRC DST --vocabulary <scene>/vocabulary.json --gt gt.npz`` and
``panogs run DST --out OUT`` run in subprocesses, and the script prints frames imported / skipped, the primitive
count, per-stage wall time (OUT/report.json) and the metrics (OUT/metrics.json). It exits non-zero when the
importer skips other frames than the ones given invalid poses. ``write_scannet_export`` is reusable on any bundle.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.io.bundle import open_bundle  # noqa: E402
from panogs_core.io.importers.common import resample_nearest  # noqa: E402
from panogs_core.synthetic import make_scene  # noqa: E402

SCANNET_COLOR_SIZE = (1296, 968)  # (width, height) of ScanNet v2 colour frames
FEATURE_DIVISOR = 4  # feature maps at a quarter of the depth resolution (LSeg / OpenScene exports)
INDEX_STEP = 10  # exports keep every 10th frame
METRICS = ("miou", "macc", "prq_thing", "prq_stuff")


@dataclass(frozen=True)
class ScanNetExport:
    """What ``write_scannet_export`` wrote."""

    root: Path
    indices: tuple[int, ...]  # frame index <i> per source frame, in order
    invalid: tuple[int, ...]  # indices whose pose file is -inf


def write_scannet_export(
    bundle: str | Path,
    dst: str | Path,
    *,
    invalid_fraction: float = 0.03,
    seed: int = 0,
    color_size: tuple[int, int] = SCANNET_COLOR_SIZE,
) -> ScanNetExport:
    """Write a bundle's frames as a ScanNet SensReader export (+ features and masks) at ``dst``.

    Args:
        bundle: Any valid bundle.
        dst: Export folder to create (``color/``, ``depth/``, ``pose/``, ``intrinsic/``, ``features/``, ``masks/``).
        invalid_fraction: Share of frames whose pose is written as ``-inf`` (at least one when > 0).
        seed: Seeds the index gaps and the choice of invalid frames.
        color_size: ``(width, height)`` the colour frames are resampled to.

    Returns:
        The indices written and those with invalid poses.
    """
    scene = open_bundle(bundle)
    dst = Path(dst)
    for sub in ("color", "depth", "pose", "intrinsic", "features", "masks"):
        (dst / sub).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    n = len(scene.frames)
    steps = INDEX_STEP * rng.choice([1, 1, 1, 1, 2, 3], size=n)  # some exported frames are missing
    indices = np.concatenate([[0], np.cumsum(steps[1:])]).astype(int)
    n_invalid = 0 if invalid_fraction <= 0 else max(1, round(invalid_fraction * n))
    invalid = set(rng.choice(indices, size=min(n_invalid, n), replace=False).tolist())
    cam = scene.camera
    _write_matrix(dst / "intrinsic" / "intrinsic_depth.txt", _K44(cam))
    _write_matrix(dst / "intrinsic" / "intrinsic_color.txt", _K44(cam.scaled(*color_size)))
    for name in ("extrinsic_depth.txt", "extrinsic_color.txt"):
        _write_matrix(dst / "intrinsic" / name, np.eye(4))
    feature_hw = (cam.height // FEATURE_DIVISOR, cam.width // FEATURE_DIVISOR)
    for index, frame in zip(indices.tolist(), scene.frames):
        pose = np.full((4, 4), -np.inf) if index in invalid else frame.T_world_cam
        _write_matrix(dst / "pose" / f"{index}.txt", pose)
        depth_mm = np.round(scene.read_depth(frame).astype(np.float64) * 1000.0)
        _imwrite(dst / "depth" / f"{index}.png", np.clip(depth_mm, 0, 65535).astype(np.uint16))
        rgb = scene.read_color(frame)
        if rgb is not None:
            big = cv2.resize(rgb, color_size, interpolation=cv2.INTER_LINEAR)
            _imwrite(dst / "color" / f"{index}.jpg", big[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
        if frame.features is not None:
            feat = resample_area(np.asarray(scene.read_features(frame), np.float32), feature_hw)
            np.save(dst / "features" / f"{index}.npy", feat.astype(np.float16))
        if frame.masks is not None:
            _imwrite(dst / "masks" / f"{index}.png", scene.read_masks(frame).astype(np.uint16))
    return ScanNetExport(root=dst, indices=tuple(indices.tolist()), invalid=tuple(sorted(invalid)))


def resample_area(feat: np.ndarray, size: tuple[int, int]) -> np.ndarray:  # (Hf, Wf, D) -> (h, w, D)
    """Block means when the size divides the map (what a strided encoder's output looks like), else nearest."""
    h_in, w_in = feat.shape[:2]
    h, w = size
    if (h_in, w_in) == (h, w):
        return feat
    if h_in % h == 0 and w_in % w == 0:
        return feat.reshape(h, h_in // h, w, w_in // w, -1).mean(axis=(1, 3))
    return resample_nearest(feat, size)


def _K44(cam: Any) -> np.ndarray:  # (4, 4) as in ScanNet's intrinsic_*.txt
    K = np.eye(4)
    K[:3, :3] = cam.K
    return K


def _write_matrix(path: Path, matrix: np.ndarray) -> None:
    rows = [" ".join("-inf" if np.isneginf(v) else f"{v:.6f}" for v in row) for row in matrix]
    path.write_text("\n".join(rows) + "\n")


def _imwrite(path: Path, image: np.ndarray, params: list[int] | None = None) -> None:
    if not cv2.imwrite(str(path), np.ascontiguousarray(image), params or []):
        raise OSError(f"could not write {path}")


def _panogs(*args: str) -> tuple[str, float]:
    """Run the panogs CLI in a subprocess; returns (stdout, seconds). Raises with its stderr on failure."""
    exe = Path(sys.executable).with_name("panogs")
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-m", "panogs_core.cli"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run([*cmd, *args], capture_output=True, text=True, env=env, cwd=ROOT, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"panogs {' '.join(args)} exited {proc.returncode}:\n{proc.stderr[-4000:]}")
    return proc.stdout, time.perf_counter() - t0


def round_trip(
    *,
    preset: str = "tiny",
    difficulty: str = "default",
    seed: int = 0,
    work: str | Path = ROOT / "bench" / "results" / "scannet_like",
    invalid_fraction: float = 0.03,
    overrides: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Synthesise, export as ScanNet, import and run with the CLI; returns the numbers the script prints."""
    work = Path(work).resolve() / f"{preset}-{difficulty}-{seed}"  # the CLI runs with the repository as cwd
    if work.exists():
        shutil.rmtree(work)
    t0 = time.perf_counter()
    synthetic = make_scene(
        work / "synthetic",
        preset=preset,
        difficulty=difficulty,
        seed=seed,
        feature_space="clip-vit-b32",
        with_geometry=False,
    )
    synth_s = time.perf_counter() - t0
    export = write_scannet_export(
        synthetic, work / "scans" / "scene0000_00", invalid_fraction=invalid_fraction, seed=seed
    )
    gt = work / "gt.npz"
    shutil.copyfile(synthetic / "gt" / "labels.npz", gt)
    bundle, out = work / "bundle", work / "run"
    import_out, import_s = _panogs(
        "import", "scannet", str(export.root), str(bundle), "--vocabulary", str(synthetic / "vocabulary.json"),
        "--gt", str(gt),
    )  # fmt: skip
    run_args = ["run", str(bundle), "--out", str(out), "--quiet"]
    for pair in overrides:
        run_args += ["--set", pair]
    _, run_s = _panogs(*run_args)
    manifest = json.loads((bundle / "scene.json").read_text())
    imported = [int(f["id"]) for f in manifest["frames"]]
    skipped = sorted(set(export.indices) - set(imported))
    match = re.search(r"skipped (\d+) frames with invalid poses", import_out)
    report = json.loads((out / "report.json").read_text())
    metrics_path = out / "metrics.json"
    return {
        "preset": preset,
        "difficulty": difficulty,
        "seed": seed,
        "frames_source": len(export.indices),
        "frames_imported": len(imported),
        "frames_skipped": skipped,
        "frames_skipped_reported": int(match.group(1)) if match else 0,
        "frames_invalid_pose": list(export.invalid),
        "primitives": report["num_primitives"],
        "gt_points": int(np.load(gt)["semantic"].shape[0]),
        "stages": {s["stage"]: s["wall_s"] for s in report["stages"]},
        "peak_rss_mb": report["peak_rss_mb"],
        "synth_s": round(synth_s, 2),
        "import_s": round(import_s, 2),
        "run_s": round(run_s, 2),
        "metrics": json.loads(metrics_path.read_text()) if metrics_path.is_file() else None,
    }


def format_summary(r: dict[str, Any]) -> str:
    """The printed report of one round trip."""
    lines = [
        f"scannet-like round trip: preset {r['preset']}, difficulty {r['difficulty']}, seed {r['seed']}",
        f"frames: {r['frames_source']} exported, {r['frames_imported']} imported, "
        f"{len(r['frames_skipped'])} skipped {r['frames_skipped']} (invalid poses written: {r['frames_invalid_pose']}, "
        f"importer reported {r['frames_skipped_reported']})",
        f"primitives: {r['primitives']} (ground truth: {r['gt_points']} points, transferred by nearest primitive)",
        f"time: synthesise {r['synth_s']:.1f} s, import {r['import_s']:.1f} s, run {r['run_s']:.1f} s "
        f"(process), peak RSS {r['peak_rss_mb']:.0f} MB",
        "stages (s): " + "  ".join(f"{k} {v:.2f}" for k, v in r["stages"].items()),
    ]
    for mode, m in (r["metrics"] or {}).items():
        values = "  ".join(f"{k} {'n/a' if m[k] is None else f'{m[k]:.3f}'}" for k in METRICS)
        lines.append(f"{mode:>8}: {values}")
    if not r["metrics"]:
        lines.append("no metrics.json: the run was not scored")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--difficulty", default="default")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=str(ROOT / "bench" / "results" / "scannet_like"))
    ap.add_argument("--invalid-fraction", type=float, default=0.03)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="pipeline override")
    ap.add_argument("--json", help="also write the numbers to this JSON file")
    args = ap.parse_args()
    result = round_trip(
        preset=args.preset,
        difficulty=args.difficulty,
        seed=args.seed,
        work=args.work,
        invalid_fraction=args.invalid_fraction,
        overrides=tuple(args.set),
    )
    print(format_summary(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    if result["frames_skipped"] != result["frames_invalid_pose"]:
        raise SystemExit("the importer skipped other frames than those with invalid poses")


if __name__ == "__main__":
    main()
