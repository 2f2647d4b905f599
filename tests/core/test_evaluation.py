"""Evaluation (evaluation/metrics.py): hand-computed cases for both modes, and the reference loop as an oracle."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from panogs_core.errors import InputError, ShapeError
from panogs_core.evaluation.metrics import evaluate, semantic_scores, transfer_to_points
from panogs_core.language.label_sets import builtin_vocabulary
from panogs_core.types import Vocabulary

A = np.array


def _wall_chair_table() -> Vocabulary:
    return Vocabulary(names=("wall", "chair", "table"), kinds=("stuff", "thing", "thing"))


def _case_cumulative() -> tuple[np.ndarray, ...]:
    """12 points: a perfect chair, a table predicted on the wall, the wall predicted on the table."""
    gt_sem = A([1, 1, 1, 1, 2, 2, 2, 2, 0, 0, 0, 0])
    gt_ins = A([10, 10, 10, 10, 20, 20, 20, 20, 30, 30, 30, 30])
    pred_sem = A([1, 1, 1, 1, 0, 0, 0, 0, 2, 2, 2, 2])
    pred_ins = A([1, 1, 1, 1, 5, 5, 5, 5, 2, 2, 2, 2])
    return pred_sem, pred_ins, gt_sem, gt_ins


class TestEvaluateStandard:
    def test_smoke(self) -> None:
        m = evaluate(*_case_cumulative(), _wall_chair_table())
        # mIoU: wall 0, chair 1, table 0 -> 1/3; mAcc the same.
        assert m.miou == pytest.approx(1 / 3)
        assert m.macc == pytest.approx(1 / 3)
        # Things, counters per class: chair TP=1 (IoU 1) -> PQ 1; table: its only prediction has IoU 0 with
        # the GT table -> FP=1, FN=1 -> PQ = 0 / (0 + 0.5 + 0.5) = 0. PRQ(T) = (1 + 0) / 2.
        assert m.prq_thing == pytest.approx(0.5)
        assert m.sq_thing == pytest.approx(0.5)
        assert m.rq_thing == pytest.approx(0.5)
        # Stuff: the wall union {8..11} against the predicted wall union {4..7}: IoU 0 -> FP=1, FN=1 -> 0.
        assert m.prq_stuff == pytest.approx(0.0)
        assert m.class_pq == {"chair": 1.0, "table": 0.0, "wall": 0.0}
        assert m.num_points == 12
        assert m.mode == "standard"

    def test_unannotated_and_instance_minus_one(self) -> None:
        vocab = Vocabulary(names=("floor", "chair"), kinds=("stuff", "thing"))
        gt_sem = A([1, 1, 1, 1, -1, -1, 0, 0, 0, 0])
        gt_ins = A([7, 7, 7, 7, -1, -1, -1, -1, -1, -1])
        pred_sem = A([1, 1, 1, 1, 1, 1, 0, 0, 0, 0])
        pred_ins = A([3, 3, -1, -1, 3, 3, 4, 4, 4, 4])
        m = evaluate(pred_sem, pred_ins, gt_sem, gt_ins, vocab)
        # Points 4, 5 (unannotated) are dropped: 8 points. mIoU: chair 4/4, floor 4/4.
        assert m.num_points == 8
        assert m.miou == pytest.approx(1.0)
        assert m.macc == pytest.approx(1.0)
        # Chair: GT {0,1,2,3}; segment (chair, 3) = {0,1} (points 2, 3 have no instance, so no segment):
        # IoU 2/4 = 0.5 > 0.25 -> TP -> PQ = 0.5 / 1 = 0.5.
        assert m.prq_thing == pytest.approx(0.5)
        assert m.sq_thing == pytest.approx(0.5)
        # At 0.5 (strict >): no match; FN=1, and the segment is FP (half of its 4 points on void is not
        # "more than half") -> PQ 0.
        assert m.prq_thing_50 == pytest.approx(0.0)
        # Floor: one segment per class, {6..9} vs {6..9}, IoU 1 (GT instance ids do not matter for stuff).
        assert m.prq_stuff == pytest.approx(1.0)

    def test_threshold_is_strict(self) -> None:
        vocab = _wall_chair_table()
        # Chair GT {0,1,2,3}; predicted chair {0,1,4,5,6,7}: IoU = 2 / 8 = 0.25, not > 0.25.
        gt_sem, gt_ins = A([1, 1, 1, 1, 0, 0, 0, 0]), A([1, 1, 1, 1, 9, 9, 9, 9])
        pred_sem, pred_ins = A([1, 1, 0, 0, 1, 1, 1, 1]), A([5, 5, 6, 6, 5, 5, 5, 5])
        for mode in ("standard", "paper"):
            m = evaluate(pred_sem, pred_ins, gt_sem, gt_ins, vocab, mode=mode)  # type: ignore[arg-type]
            assert m.prq_thing == pytest.approx(0.0), mode
            m = evaluate(pred_sem, pred_ins, gt_sem, gt_ins, vocab, mode=mode, iou_threshold=0.24)  # type: ignore[arg-type]
            assert m.prq_thing == pytest.approx(0.25 / 1.0), mode  # TP with IoU 0.25, no FP, no FN

    def test_one_to_one_greedy_by_iou(self) -> None:
        vocab = _wall_chair_table()
        # Two GT chairs, A = {0..3}, B = {4..7}; prediction p = {2..7} overlaps A (2/8 = 0.25 -> no) and
        # B (4/6); prediction q = {0, 1}: A 2/4 = 0.5. Matches: (B, p) 0.667 and (A, q) 0.5
        # -> PQ = 1.1667 / 2.
        gt_sem, gt_ins = A([1] * 8), A([0, 0, 0, 0, 1, 1, 1, 1])
        pred_sem, pred_ins = A([1] * 8), A([8, 8, 3, 3, 3, 3, 3, 3])
        m = evaluate(pred_sem, pred_ins, gt_sem, gt_ins, vocab)
        assert m.prq_thing == pytest.approx((4 / 6 + 0.5) / 2)

    def test_void_majority_prediction_is_not_fp(self) -> None:
        vocab = _wall_chair_table()
        # GT chair {0,1}; prediction: chair 1 = {0,1} (TP), chair 2 = {2,3,4} of which 3, 4 are unannotated
        # -> more than half void -> not FP. PQ = 1.
        gt_sem, gt_ins = A([1, 1, 0, -1, -1]), A([4, 4, 0, -1, -1])
        pred_sem, pred_ins = A([1, 1, 1, 1, 1]), A([1, 1, 2, 2, 2])
        assert evaluate(pred_sem, pred_ins, gt_sem, gt_ins, vocab).prq_thing == pytest.approx(1.0)
        # Chair 2 on {2, 3} only: exactly half void -> FP: PQ = 1 / (1 + 0.5).
        pred_ins2 = A([1, 1, 2, 2, 7])
        pred_sem2 = A([1, 1, 1, 1, 2])
        assert evaluate(pred_sem2, pred_ins2, gt_sem, gt_ins, vocab).prq_thing == pytest.approx(1 / 1.5)

    def test_ignore_classes_and_nan(self) -> None:
        vocab = _wall_chair_table()
        m = evaluate(*_case_cumulative(), vocab, ignore_classes=("Table", 0))
        assert m.miou == pytest.approx(1.0)
        assert set(m.class_iou) == {"chair"}
        assert m.prq_thing == pytest.approx(1.0)
        assert math.isnan(m.prq_stuff)
        doc = m.to_json()
        assert doc["prq_stuff"] is None
        json.dumps(doc)


class TestEvaluatePaper:
    def test_cumulative_counters(self) -> None:
        m = evaluate(*_case_cumulative(), _wall_chair_table(), mode="paper")
        # Reference loop over thing classes [chair, table], counters NOT reset:
        #   chair: TP=1, FN=0, iou_sum=1, FP=0 -> den 1 -> PQ += 1, RQ += 1, SQ += 1, n_valid = 1
        #   table: GT 20 vs prediction 2 -> IoU 0 -> FN=1 (cumulative), FP=1 (per class), TP=1, iou_sum=1
        #          -> den = 1 + 0.5 + 0.5 = 2 -> PQ += 0.5, RQ += 0.5, SQ += 1 / 1, n_valid = 2
        # PRQ(T) = 1.5 / 2 = 0.75 (standard mode: 0.5).
        assert m.prq_thing == pytest.approx(0.75)
        assert m.rq_thing == pytest.approx(0.75)
        assert m.sq_thing == pytest.approx(1.0)
        assert m.class_pq == {"chair": 1.0, "table": 0.5, "wall": 0.0}
        assert m.prq_stuff == pytest.approx(0.0)
        std = evaluate(*_case_cumulative(), _wall_chair_table(), mode="standard")
        assert std.prq_thing != m.prq_thing

    def test_unannotated_and_instance_minus_one(self) -> None:
        vocab = Vocabulary(names=("floor", "chair"), kinds=("stuff", "thing"))
        gt_sem = A([1, 1, 1, 1, -1, -1, 0, 0, 0, 0])
        gt_ins = A([7, 7, 7, 7, -1, -1, -1, -1, -1, -1])
        pred_sem = A([1, 1, 1, 1, 1, 1, 0, 0, 0, 0])
        pred_ins = A([3, 3, -1, -1, 3, 3, 4, 4, 4, 4])
        m = evaluate(pred_sem, pred_ins, gt_sem, gt_ins, vocab, mode="paper")
        # Nothing masked: chair I = 4, U = |{0..5}| = 6 -> 2/3; floor 1. mIoU = 5/6; mAcc = 1.
        assert m.miou == pytest.approx(5 / 6)
        assert m.macc == pytest.approx(1.0)
        assert m.num_points == 10
        # Chair predictions, ascending ids: -1 = {2,3} (an instance like any other), 3 = {0,1,4,5}.
        # GT 7 = {0,1,2,3}: IoU(-1) = 2/4 = 0.5, IoU(3) = 2/6 -> -1 wins, TP, iou_sum 0.5; 3 left -> FP=1.
        # PQ = 0.5 / (1 + 0.5) = 1/3; SQ = 0.5; RQ = 2/3.
        assert m.prq_thing == pytest.approx(1 / 3)
        assert m.sq_thing == pytest.approx(0.5)
        assert m.rq_thing == pytest.approx(2 / 3)
        # At 0.5 (strict): FN=1, FP=2 -> PQ 0.
        assert m.prq_thing_50 == pytest.approx(0.0)
        assert m.prq_stuff == pytest.approx(1.0)

    def test_paper_split_for_builtin_vocabularies(self) -> None:
        vocab = builtin_vocabulary("scannet20")
        cabinet, counter = vocab.names.index("cabinet"), vocab.names.index("counter")
        # A perfect cabinet: a thing by kind, but stuff in the reference's effective split (docs/method.md §8.2).
        sem, ins = A([cabinet] * 4), A([0] * 4)
        std = evaluate(sem, ins, sem, ins, vocab)
        pap = evaluate(sem, ins, sem, ins, vocab, mode="paper")
        assert std.prq_thing == pytest.approx(1.0)
        assert math.isnan(std.prq_stuff)
        assert pap.prq_stuff == pytest.approx(1.0)
        assert math.isnan(pap.prq_thing)
        # Counter: stuff in the ScanNet split, thing in the Matterport (Replica) split.
        sem = A([counter] * 4)
        assert evaluate(sem, ins, sem, ins, vocab, mode="paper").prq_stuff == pytest.approx(1.0)
        mp = builtin_vocabulary("matterport21")
        assert evaluate(sem, ins, sem, ins, mp, mode="paper").prq_thing == pytest.approx(1.0)

    def test_other_classes_excluded(self) -> None:
        vocab = builtin_vocabulary("scannet20")
        other = vocab.names.index("otherfurniture")
        wall = vocab.names.index("wall")
        gt = A([other, other, wall, wall])
        pred = A([wall, wall, wall, wall])
        ins = A([0, 0, 1, 1])
        # Paper: otherfurniture left out; its points still widen the wall union: wall IoU 2/4.
        assert evaluate(pred, ins, gt, ins, vocab, mode="paper").miou == pytest.approx(0.5)
        # Standard: every class present counts: (wall 2/4 + otherfurniture 0) / 2.
        assert evaluate(pred, ins, gt, ins, vocab).miou == pytest.approx(0.25)

    def test_matches_reference_loop(self) -> None:
        vocab = Vocabulary(
            names=("wall", "floor", "chair", "table", "sofa"), kinds=("stuff", "stuff", "thing", "thing", "thing")
        )
        rng = np.random.default_rng(3)
        for _ in range(20):
            n = 60
            gt_sem, pred_sem = rng.integers(-1, 5, n), rng.integers(-1, 5, n)
            gt_ins, pred_ins = rng.integers(-1, 4, n), rng.integers(-1, 4, n)
            m = evaluate(pred_sem, pred_ins, gt_sem, gt_ins, vocab, mode="paper")
            cases = (
                ([2, 3, 4], 0.25, m.prq_thing),
                ([0, 1], 0.25, m.prq_stuff),
                ([2, 3, 4], 0.5, m.prq_thing_50),
                ([0, 1], 0.5, m.prq_stuff_50),
            )
            for classes, threshold, value in cases:
                expected = _reference_panoptic(pred_sem, pred_ins, gt_sem, gt_ins, classes, threshold)
                assert value == pytest.approx(expected) if not math.isnan(value) else expected is None


def _reference_panoptic(
    pred_sem: np.ndarray,
    pred_ins: np.ndarray,
    gt_sem: np.ndarray,
    gt_ins: np.ndarray,
    classes: list[int],
    threshold: float,
) -> float | None:
    """docs/method.md §8.2, written as the plain loop (the oracle)."""
    tp = fn = n_valid = 0
    iou_sum = pq = 0.0
    for c in classes:
        pm, gm = pred_sem == c, gt_sem == c
        remaining = sorted(set(pred_ins[pm].tolist()))
        for g in sorted(set(gt_ins[gm].tolist())):
            gmask = gm & (gt_ins == g)
            best, arg = 0.0, None
            for r in remaining:
                rmask = pm & (pred_ins == r)
                iou = np.sum(gmask & rmask) / np.sum(gmask | rmask)
                if iou > best:
                    best, arg = iou, r
            if best > threshold:
                tp += 1
                iou_sum += best
                remaining.remove(arg)
            else:
                fn += 1
        fp = len(remaining)
        if tp + fp + fn > 0:
            pq += iou_sum / (tp + 0.5 * fp + 0.5 * fn)
            n_valid += 1
    return pq / n_valid if n_valid else None


class TestEvaluateExceptions:
    def test_exception(self) -> None:
        vocab = _wall_chair_table()
        ok = A([0, 1])
        with pytest.raises(ShapeError, match="pred_instance"):
            evaluate(ok, A([0]), ok, ok, vocab)
        with pytest.raises(InputError, match=r"class ids must be in \[-1, 3\)"):
            evaluate(A([0, 3]), ok, ok, ok, vocab)
        with pytest.raises(InputError, match="integer labels"):
            evaluate(A([0.5, 1.0]), ok, ok, ok, vocab)
        with pytest.raises(InputError, match="mode"):
            evaluate(ok, ok, ok, ok, vocab, mode="coco")  # type: ignore[arg-type]
        with pytest.raises(InputError, match="iou_threshold"):
            evaluate(ok, ok, ok, ok, vocab, iou_threshold=1.0)
        with pytest.raises(InputError, match="'sofa' is not a class"):
            evaluate(ok, ok, ok, ok, vocab, ignore_classes=("sofa",))

    def test_float_ground_truth_is_accepted(self) -> None:
        # Reference ScanNet GT arrays are float64 with -0.0.
        vocab = _wall_chair_table()
        gt = A([-0.0, 1.0, 1.0])
        m = evaluate(A([0, 1, 1]), A([0, 1, 1]), gt, A([0.0, 2.0, 2.0]), vocab)
        assert m.miou == pytest.approx(1.0)


class TestSemanticScores:
    def test_smoke(self) -> None:
        iou, acc, present = semantic_scores(A([0, 0, 1, -1]), A([0, 1, 1, 2]), 3)
        # class 0: I 1, U 2; class 1: I 1, U 2; class 2: I 0, U 1.
        np.testing.assert_allclose(iou, [0.5, 0.5, 0.0])
        np.testing.assert_allclose(acc, [1.0, 0.5, 0.0])
        assert present.tolist() == [True, True, True]


class TestTransferToPoints:
    def test_smoke(self) -> None:
        prim = A([[0.0, 0, 0], [1.0, 0, 0], [0.0, 2, 0]])
        query = A([[0.9, 0.1, 0], [0.1, 1.5, 0], [0.0, 0.0, 0.2], [5.0, 0, 0]])
        sem, ins = transfer_to_points(prim, query, A([3, 4, 5]), A([10, 11, 12]))
        assert sem.tolist() == [4, 5, 3, 4]
        assert ins.tolist() == [11, 12, 10, 11]

    def test_cardinality(self) -> None:
        prim = np.zeros((2, 3))
        (feat,) = transfer_to_points(prim, np.zeros((5, 3)), np.ones((2, 4)))
        assert feat.shape == (5, 4)

    def test_exception(self) -> None:
        with pytest.raises(ShapeError, match="primitive_points"):
            transfer_to_points(np.zeros((0, 3)), np.zeros((1, 3)))
        with pytest.raises(ShapeError, match="query_points"):
            transfer_to_points(np.zeros((2, 3)), np.zeros((1, 2)))
        with pytest.raises(ShapeError, match="values"):
            transfer_to_points(np.zeros((2, 3)), np.zeros((1, 3)), np.zeros(3))
