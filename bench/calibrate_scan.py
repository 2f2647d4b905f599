"""Calibrate the realistic ``scan`` preset against the held-out real ScanNet capture.

Usage:
    python bench/calibrate_scan.py [--difficulties easy default hard] [--seeds 0 1]
                                   [--work bench/results/calibrate] [--regen] [--markdown]

For every difficulty and seed, makes ``panogs synth --preset scan`` scene (kept in ``--work``; ``--regen``
makes it again), runs the pipeline's stages up to fusion (primitives = the geometry's vertices, visibility over
the key frames, fused features) and prints, next to the real capture's figures:

(a) the scene's statistics: primitives, share of primitives seen by no key frame, mean key views per seen
    primitive, class shares of all primitives (unannotated included), cabinet instances;
(b) the simple baseline "fused-feature argmax": per primitive, the class whose text embedding has the highest
    cosine with the fused feature; a primitive seen by no key frame gets -1 ("no fill", always wrong) or the
    class of its nearest seen primitive ("fill"). mIoU is ``panogs_core.evaluation.metrics.evaluate`` in standard mode
    (unannotated ground truth left out, classes present in the ground truth averaged).

``--markdown`` prints the tables as markdown (docs/synthetic.md holds them with this script's command line).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.evaluation.metrics import evaluate  # noqa: E402
from panogs_core.io.bundle import Bundle, open_bundle  # noqa: E402
from panogs_core.pipeline import stage_table as stages  # noqa: E402
from panogs_core.pipeline.config import PipelineConfig  # noqa: E402
from panogs_core.pipeline.run import resolve_scene_vocabulary  # noqa: E402
from panogs_core.synthetic import make_scene  # noqa: E402

# Measured on the held-out real capture (ScanNet-style mesh and key frames every 20th frame).
REAL_STATS = {"primitives": 81_369, "unseen": 0.122, "views": 5.2, "cabinets": 7}
REAL_SHARES = {
    "wall": 0.171, "floor": 0.126, "cabinet": 0.121, "curtain": 0.068, "sofa": 0.063, "table": 0.055,
    "bed": 0.036, "desk": 0.023, "door": 0.017, "refrigerator": 0.017, "window": 0.010,
    "otherfurniture": 0.008, "counter": 0.006, "toilet": 0.006, "sink": 0.004, "unannotated": 0.269,
}  # fmt: skip
REAL_MIOU = {"easy": (0.889, 0.829), "default": (0.583, 0.560), "hard": (0.371, 0.362)}  # (fill, no fill)
STAND_IN = {"otherfurniture": "bookshelf"}  # the synthetic catalogue's class in the place of a real one


@dataclass(frozen=True)
class Result:
    """Statistics and baseline scores of one scene."""

    difficulty: str
    seed: int
    primitives: int
    unseen: float
    views: float
    shares: dict[str, float]
    cabinets: int
    miou_fill: float
    miou_no_fill: float
    seconds_make: float
    seconds_fuse: float


def _quiet(done: int, total: int) -> None:
    """A progress callback that reports nothing."""


def fused_argmax(scene: Bundle) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Stages up to fusion, then the argmax class per primitive.

    Returns:
        Primitive points ``(N, 3)``, argmax class ``(N,)`` (-1 where unseen), key views per primitive ``(N,)``,
        and the seconds the stages took.
    """
    t0 = time.perf_counter()
    cfg = PipelineConfig()
    prims = stages.primitives(scene, cfg, _quiet)
    vis = stages.visibility(scene, prims, cfg, _quiet)
    fused = stages.fusion(scene, vis, prims, cfg, _quiet)
    vocab = resolve_scene_vocabulary(scene, None)
    emb = np.asarray(vocab.embeddings, dtype=np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    feats = np.asarray(fused.features, dtype=np.float32)
    norm = np.linalg.norm(feats, axis=1)
    seen = np.asarray(fused.seen_count) > 0
    pred = np.where(seen & (norm > 0), (feats @ emb.T).argmax(axis=1), -1)
    return np.asarray(prims.points), pred, np.asarray(fused.seen_count), time.perf_counter() - t0


def fill_nearest(points: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Give each unpredicted (-1) primitive the class of its nearest predicted primitive."""
    known = np.flatnonzero(pred >= 0)
    out = pred.copy()
    if len(known) and len(known) < len(pred):
        missing = np.flatnonzero(pred < 0)
        out[missing] = pred[known[cKDTree(points[known]).query(points[missing])[1]]]
    return out


def miou(pred: np.ndarray, scene: Bundle) -> float:
    """Standard-mode mIoU of a per-primitive class prediction (geometry ground truth, one label per vertex)."""
    gt, vocab = scene.read_ground_truth(), resolve_scene_vocabulary(scene, None)
    assert gt is not None
    return evaluate(pred, pred, gt.semantic, gt.instance, vocab, mode="standard").miou


def measure(work: Path, difficulty: str, seed: int, regen: bool) -> Result:
    """Make (or reuse) one scan scene and measure it."""
    root = work / f"scan-{difficulty}-{seed}"
    t0 = time.perf_counter()
    if regen or not (root / "scene.json").is_file():
        shutil.rmtree(root, ignore_errors=True)  # no frame files of an older, longer scene may stay behind
        make_scene(root, preset="scan", difficulty=difficulty, seed=seed)
    seconds_make = time.perf_counter() - t0
    scene = open_bundle(root)
    points, pred, views, seconds_fuse = fused_argmax(scene)
    gt, vocab = scene.read_ground_truth(), resolve_scene_vocabulary(scene, None)
    assert gt is not None
    names = np.array([*vocab.names, "unannotated"])  # index -1 is the last
    labels, counts = np.unique(gt.semantic, return_counts=True)
    shares = {str(names[c]): n / len(gt.semantic) for c, n in zip(labels, counts)}
    cabinet = vocab.names.index("cabinet")
    seen = views > 0
    return Result(
        difficulty=difficulty,
        seed=seed,
        primitives=len(points),
        unseen=float(1.0 - seen.mean()),
        views=float(views[seen].mean()),
        shares=shares,
        cabinets=len(np.unique(gt.instance[gt.semantic == cabinet])),
        miou_fill=miou(fill_nearest(points, pred), scene),
        miou_no_fill=miou(pred, scene),
        seconds_make=seconds_make,
        seconds_fuse=seconds_fuse,
    )


def _row(cells: Sequence[object], markdown: bool) -> str:
    if markdown:
        return "| " + " | ".join(str(c) for c in cells) + " |"
    return "  ".join(f"{c!s:>14}" for c in cells)


def stats_table(results: list[Result], markdown: bool) -> list[str]:
    """Lines of the statistics table: the real capture's figures, then one column per scene."""
    head = ["", "real", *[f"{r.difficulty} s{r.seed}" for r in results]]
    lines = [_row(head, markdown)] + ([_row(["---"] * len(head), markdown)] if markdown else [])
    rows = [
        ("primitives", f"{REAL_STATS['primitives']}", [f"{r.primitives}" for r in results]),
        ("seen by no key frame", f"{REAL_STATS['unseen']:.3f}", [f"{r.unseen:.3f}" for r in results]),
        ("key views per seen primitive", f"{REAL_STATS['views']:.1f}", [f"{r.views:.1f}" for r in results]),
        ("cabinet instances", f"{REAL_STATS['cabinets']}", [f"{r.cabinets}" for r in results]),
    ]
    lines += [_row([name, real, *ours], markdown) for name, real, ours in rows]
    # the real classes first, then any other class a scene has (bookshelf is otherfurniture's stand-in)
    extra = sorted({c for r in results for c in r.shares} - set(REAL_SHARES) - set(STAND_IN.values()))
    for cls in [*REAL_SHARES, *extra]:
        ours_name = STAND_IN.get(cls, cls)
        label = f"share {cls}" + (f" ({ours_name})" if ours_name != cls else "")
        real = f"{REAL_SHARES[cls]:.3f}" if cls in REAL_SHARES else "-"
        lines.append(_row([label, real, *[f"{r.shares.get(ours_name, 0.0):.3f}" for r in results]], markdown))
    return lines


def baseline_table(results: list[Result], markdown: bool) -> list[str]:
    """Lines of the baseline table: mIoU with and without fill per difficulty, real against ours."""
    head = ["difficulty", "real fill / no fill", "ours fill / no fill (mean)", "per seed fill / no fill"]
    lines = [_row(head, markdown)] + ([_row(["---"] * len(head), markdown)] if markdown else [])
    for difficulty in dict.fromkeys(r.difficulty for r in results):
        rs = [r for r in results if r.difficulty == difficulty]
        target = REAL_MIOU.get(difficulty, (float("nan"), float("nan")))
        fill, no_fill = np.mean([r.miou_fill for r in rs]), np.mean([r.miou_no_fill for r in rs])
        per_seed = ", ".join(f"s{r.seed}: {r.miou_fill:.3f} / {r.miou_no_fill:.3f}" for r in rs)
        lines.append(_row([difficulty, f"{target[0]:.3f} / {target[1]:.3f}", f"{fill:.3f} / {no_fill:.3f}", per_seed],
                          markdown))  # fmt: skip
    return lines


def report(results: list[Result], markdown: bool) -> None:
    """Print the statistics table, the baseline table and the times."""
    print("\n".join(stats_table(results, markdown)))
    print()
    print("\n".join(baseline_table(results, markdown)))
    print()
    times = ", ".join(f"{r.difficulty} s{r.seed}: {r.seconds_make:.0f} s + {r.seconds_fuse:.0f} s" for r in results)
    print(f"seconds (make, 0 when reused + stages to fusion): {times}")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--difficulties", nargs="+", default=["easy", "default", "hard"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--work", type=Path, default=ROOT / "bench" / "results" / "calibrate")
    parser.add_argument("--regen", action="store_true", help="make the scenes again even if present")
    parser.add_argument("--markdown", action="store_true", help="print markdown tables")
    args = parser.parse_args(argv)
    results = [measure(args.work, d, s, args.regen) for d in args.difficulties for s in args.seeds]
    report(results, args.markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
