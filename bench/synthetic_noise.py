"""What the synthetic noise model does to a scene, measured from the bundle alone (no pipeline).

Usage:
    python bench/synthetic_noise.py BUNDLE [BUNDLE ...]
    python bench/synthetic_noise.py --make small --difficulties easy default hard --seed 1 --space minilm-l6

Every ground-truth point is projected into every key frame with the pipeline's own depth test (stage 2), and
each (point, frame) observation reads the feature cell and the mask id it lands on. Printed per bundle:

- observation accuracy: argmax of the observed feature cell against the vocabulary == the point's class;
- point accuracy: the same for the mean feature over all of a point's observations;
- same-class instance cosine: cosine between the mean features of two different instances of one class
  (median over pairs) — near 1 in real LSeg / OpenSeg maps, where instances of a class look alike;
- other-class cosine: the same between instances of different classes (for scale);
- mask purity: per (frame, mask), the share of its observed points that belong to its majority instance;
- mask merges: the share of masks with a second instance holding over 20 % of the mask's points.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.io.bundle import open_bundle
from panogs_core.stages.fusion import feature_cells
from panogs_core.stages.visibility import VisibilityConfig, compute_visibility
from panogs_core.synthetic import make_scene


def measure(bundle: Path) -> dict[str, float]:
    """The numbers of the module docstring for one bundle with ground truth and vocabulary embeddings."""
    scene = open_bundle(bundle)
    gt = scene.read_ground_truth()
    vocab = scene.vocabulary
    if gt is None or vocab is None or vocab.embeddings is None:
        raise SystemExit(f"{bundle}: needs gt/labels.npz and vocabulary embeddings")
    points = gt.points if gt.points is not None else scene.read_geometry().points  # type: ignore[union-attr]
    emb = vocab.embeddings / np.linalg.norm(vocab.embeddings, axis=1, keepdims=True)
    vis = compute_visibility(scene, points, VisibilityConfig())
    frames = {f.id: f for f in scene.frames}
    n = len(points)
    feat_sum = np.zeros((n, emb.shape[1]), np.float64)
    hits = correct = 0
    purity: list[float] = []
    merged = 0
    for v, fid in enumerate(vis.frame_ids):
        idx, row, col = vis.frame(v)
        frame = frames[fid]
        if frame.features is not None and len(idx):
            fmap = scene.read_features(frame).astype(np.float32)
            cells = feature_cells(row, col, (scene.camera.height, scene.camera.width), fmap.shape[:2])
            obs = fmap.reshape(-1, fmap.shape[2])[cells]
            np.add.at(feat_sum, idx, obs)
            correct += int(np.sum((obs @ emb.T).argmax(1) == gt.semantic[idx]))
            hits += len(idx)
        if frame.masks is not None and len(idx):
            masks = scene.read_masks(frame)
            mid = masks.reshape(-1)[feature_cells(row, col, (scene.camera.height, scene.camera.width),
                                                  masks.shape)]  # fmt: skip
            inside = mid > 0
            for m in np.unique(mid[inside]):
                _, counts = np.unique(gt.instance[idx[inside][mid[inside] == m]], return_counts=True)
                counts = np.sort(counts)[::-1]
                purity.append(counts[0] / counts.sum())
                merged += int(len(counts) > 1 and counts[1] > 0.2 * counts.sum())
    seen = np.linalg.norm(feat_sum, axis=1) > 0
    point_acc = float(np.mean((feat_sum[seen] @ emb.T).argmax(1) == gt.semantic[seen]))
    same, other = _instance_cosines(feat_sum, gt.semantic, gt.instance, seen, vocab.kinds)
    return {
        "observation accuracy": correct / max(hits, 1),
        "point accuracy": point_acc,
        "same-class instance cosine": same,
        "other-class instance cosine": other,
        "mask purity": float(np.mean(purity)),
        "masks merging instances": merged / max(len(purity), 1),
    }


def _instance_cosines(
    feat_sum: np.ndarray, semantic: np.ndarray, instance: np.ndarray, seen: np.ndarray, kinds: tuple[str, ...]
) -> tuple[float, float]:
    """Median cosine between mean features of thing instances: same class, and different classes."""
    ids = [i for i in np.unique(instance[seen]) if i >= 0]
    means, classes = [], []
    for i in ids:
        member = seen & (instance == i)
        cls = int(np.bincount(semantic[member]).argmax())
        if kinds[cls] != "thing":
            continue
        mean = feat_sum[member].sum(0)
        means.append(mean / np.linalg.norm(mean))
        classes.append(cls)
    m, c = np.array(means), np.array(classes)
    cos = m @ m.T
    pair = ~np.eye(len(c), dtype=bool)
    same = pair & (c[:, None] == c[None, :])
    return float(np.median(cos[same])), float(np.median(cos[pair & ~same]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bundles", nargs="*", type=Path)
    ap.add_argument("--make", metavar="PRESET", help="synthesise scenes of this preset first")
    ap.add_argument("--difficulties", nargs="+", default=["easy", "default", "hard"])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--space", default="minilm-l6")
    ap.add_argument("--work", type=Path, default=Path("bench/results/noise"))
    args = ap.parse_args()
    bundles = list(args.bundles)
    if args.make:
        for difficulty in args.difficulties:
            out = args.work / f"{args.make}-{difficulty}-{args.seed}-{args.space}"
            if not (out / "scene.json").is_file():
                make_scene(out, preset=args.make, difficulty=difficulty, seed=args.seed, feature_space=args.space)
            bundles.append(out)
    if not bundles:
        ap.error("give bundles or --make PRESET")
    results = {(f"{b.parent.name}/{b.name}" if b.name == "scene" else b.name): measure(b) for b in bundles}
    keys = next(iter(results.values())).keys()
    print("| measure | " + " | ".join(results) + " |")
    print("|---|" + "---|" * len(results))
    for k in keys:
        print(f"| {k} | " + " | ".join(f"{r[k]:.3f}" for r in results.values()) + " |")


if __name__ == "__main__":
    main()
