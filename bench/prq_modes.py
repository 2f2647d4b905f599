"""Why the paper's PRQ(T) and the standard one disagree: the step from one to the other, one quirk at a time.

Usage:
    python bench/prq_modes.py BUNDLE RUN [RUN ...] [--scannet20]

For each run folder (its ``labels.npz``, scored against the bundle's per-primitive ground truth) it prints PRQ(T)
from the standard definition to the reference's, switching on one of the reference's rules per row
(docs/method.md §8.4 reads the table):

1. standard: ``evaluate(mode="standard")``;
2. the paper's thing classes (the reference's off-by-one thing mask for ScanNet-20 names, else the same);
3. the paper's matching: per ground-truth instance in id order, the remaining prediction of highest IoU, no COCO
   rule for predictions on void, thing points without a ground-truth instance counted;
4. predicted thing points without an instance (-1) form one more predicted instance per class;
5. no void: unannotated points count in the predictions' unions;
6. TP, FN and the IoU sum cumulative across classes: the paper mode, ``evaluate(mode="paper")``.

``--scannet20`` scores a synthetic room as the held-out real room was scored: class names mapped onto the
ScanNet-20 vocabulary (the catalogue's ceiling, absent there, becomes void on both sides), so that the paper's
thing set is the reference's (bed, chair, sofa, table, door, curtain, sink, bathtub: no cabinet, desk, counter,
picture, refrigerator, toilet, window or bookshelf).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.evaluation.metrics import _paper_split, _standard_pq, evaluate, paper_class_match
from panogs_core.io.bundle import open_bundle
from panogs_core.pipeline.run import resolve_scene_vocabulary
from panogs_core.types import Vocabulary

STEPS = (
    "standard",
    "+ paper thing classes",
    "+ paper matching",
    "+ instance -1 counted",
    "+ no void",
    "+ cumulative counters (paper)",
)


def paper_like_pq(
    ps: np.ndarray,  # (G,) predicted class
    pi: np.ndarray,  # (G,) predicted instance
    gs: np.ndarray,  # (G,) ground-truth class, -1 unannotated
    gi: np.ndarray,  # (G,) ground-truth instance
    classes: list[int],
    *,
    mask_void: bool,
    none_is_instance: bool,
    cumulative: bool,
    threshold: float = 0.25,
) -> float:
    """The reference's per-class matching with its rules switchable (with all three on: ``_paper_pq``)."""
    if mask_void:
        keep = gs >= 0
        ps, pi, gs, gi = ps[keep], pi[keep], gs[keep], gi[keep]
    if not none_is_instance:
        ps = np.where(pi < 0, -1, ps)
    tp = fn = 0
    iou_sum = 0.0
    terms = []
    for c in classes:
        if not cumulative:
            tp = fn = 0
            iou_sum = 0.0
        c_tp, fp, c_fn, c_iou = paper_class_match(ps, pi, gs, gi, c, threshold)
        tp, fn, iou_sum = tp + c_tp, fn + c_fn, iou_sum + c_iou
        if tp + fp + fn > 0:
            terms.append(iou_sum / (tp + 0.5 * fp + 0.5 * fn))
    return float(np.mean(terms)) if terms else float("nan")


def to_scannet20(sem: np.ndarray, vocab: Vocabulary, target: Vocabulary) -> np.ndarray:
    """Class indices of ``vocab`` as indices of ``target`` by name (absent names become -1)."""
    lut = np.array([target.names.index(n) if n in target.names else -1 for n in vocab.names] + [-1], np.int64)
    return lut[np.where(sem >= 0, sem, len(vocab.names))]


def steps(ps, pi, gs, gi, vocab: Vocabulary) -> list[float]:
    """PRQ(T) after each step of :data:`STEPS`."""
    excluded = {i for i, n in enumerate(vocab.names) if n.lower() in ("other", "otherfurniture")}
    things_paper, _ = _paper_split(vocab, excluded)
    out = [evaluate(ps, pi, gs, gi, vocab).prq_thing, _standard_pq(ps, pi, gs, gi, things_paper, 0.25, thing=True).pq]
    for mask_void, none_inst, cumulative in ((True, False, False), (True, True, False), (False, True, False)):
        out.append(paper_like_pq(ps, pi, gs, gi, things_paper, mask_void=mask_void, none_is_instance=none_inst,
                                 cumulative=cumulative))  # fmt: skip
    out.append(evaluate(ps, pi, gs, gi, vocab, mode="paper").prq_thing)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bundle")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--scannet20", action="store_true")
    args = ap.parse_args()
    scene = open_bundle(args.bundle)
    vocab = resolve_scene_vocabulary(scene, None)
    gt = scene.read_ground_truth()
    if gt is None or gt.points is not None:
        raise SystemExit("the bundle needs per-primitive ground truth")
    gs, gi = gt.semantic, gt.instance
    if args.scannet20:
        target = resolve_scene_vocabulary(scene, "scannet20")
        gs = to_scannet20(gs, vocab, target)
        gi = np.where(gs >= 0, gi, -1)
    rows = []
    for run in args.runs:
        labels = np.load(Path(run) / "labels.npz")
        ps, pi = labels["semantic"], labels["instance"]
        if args.scannet20:
            ps = to_scannet20(ps, vocab, target)
        rows.append(steps(ps, pi, gs, gi, target if args.scannet20 else vocab))
    print("| step | " + " | ".join(Path(r).name for r in args.runs) + " |")
    print("|---|" + "---:|" * len(args.runs))
    for k, name in enumerate(STEPS):
        print(f"| {name} | " + " | ".join(f"{row[k]:.3f}" for row in rows) + " |")


if __name__ == "__main__":
    main()
