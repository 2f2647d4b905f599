"""Evaluation: mIoU, mAcc and panoptic reconstruction quality PRQ(T) / PRQ(S) (docs/method.md §8).

Labels are ours: semantic = 0-based vocabulary index, -1 = unannotated / void; instance = any int64 id,
-1 = none.

Two modes, both defined here:

``standard``: panoptic quality as defined for images (COCO) and 3D panoptic reconstruction.
    * Ground-truth points with semantic -1 are left out of everything.
    * mIoU / mAcc average over the classes present in the ground truth.
    * Things: predicted segments are the (class, instance) groups with instance >= 0; ground-truth segments
      the (class, instance) groups. Per class they are matched one to one at IoU > ``iou_threshold``, greedily
      by descending IoU (unique above 0.5). TP/FP/FN are counted per class,
      PQ_c = sum IoU(TP) / (TP + FP/2 + FN/2), and PRQ(T) averages PQ_c over the thing classes present in the
      ground truth or the prediction.
    * Stuff: one segment per class, the union of everything predicted as that class against the union of the
      ground truth of that class (COCO panoptic), matched at the same threshold; PRQ(S) averages over the
      stuff classes present in the ground truth or the prediction.
    * Void for panoptic quality: unannotated points and thing points without a ground-truth instance. An
      unmatched predicted segment with more than half of its points on void is not a false positive (COCO).
    * An average over no class is NaN (``to_json`` writes null).

``paper``: the official evaluation with its quirks, reproduced exactly (docs/method.md §8.1 and §8.2):
    * nothing is masked: predictions on unannotated ground truth enlarge the union of their class;
    * TP, FN and the IoU sum accumulate across the classes of one call (things, then stuff separately), FP is
      per class, every class after the first with activity counts in the average;
    * per ground-truth instance in ascending id order, the first predicted instance with the strictly highest
      IoU wins if that IoU > threshold (strict);
    * predicted instance -1 is an instance like any other (the reference's removed-cluster id 0 is);
    * classes named "other" / "otherfurniture" are left out of every average (reference: Replica 19,
      ScanNet 20);
    * thing/stuff sets: for the built-in scannet20 / matterport21 vocabularies the effective sets of the
      reference's off-by-one thing mask (docs/method.md §8.2), otherwise the vocabulary's kinds.
    Code mapping: the reference's ScanNet classes 1..20 are our 0..19 and its unannotated 0 our -1; Replica
    classes are 0-based in both. Its predicted instance 0 (removed) is our -1 and 1..K our ids >= 0; the
    orders agree (-1 and 0 are the smallest ids), so "first best" picks the same instance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from panogs_core.errors import InputError, ShapeError
from panogs_core.language.label_sets import BUILTIN_VOCABULARIES
from panogs_core.types import GroundTruth, Vocabulary

PAPER_EXCLUDED_NAMES = ("other", "otherfurniture")
# The reference's effective thing / stuff sets (docs/method.md §8.2), 0-based (ScanNet's 1-based lists minus one).
PAPER_SPLITS: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "scannet20": ((3, 4, 5, 6, 7, 13, 17, 18), (0, 1, 2, 8, 9, 10, 11, 12, 14, 15, 16)),
    "matterport21": ((3, 4, 5, 6, 7, 11, 13, 17, 18), (0, 1, 2, 8, 9, 10, 12, 14, 15, 16, 20)),
}


@dataclass(frozen=True)
class Metrics:
    """Scene metrics, fractions in [0, 1]; NaN where no class was evaluated.

    ``class_pq`` holds PQ per evaluated class (standard); in paper mode, the term the reference adds for that
    class (with its cumulative counters).
    """

    mode: str
    iou_threshold: float
    miou: float
    macc: float
    prq_thing: float
    prq_stuff: float
    sq_thing: float
    rq_thing: float
    sq_stuff: float
    rq_stuff: float
    prq_thing_50: float  # the same at IoU > 0.5
    prq_stuff_50: float
    class_iou: dict[str, float]
    class_acc: dict[str, float]
    class_pq: dict[str, float]
    num_points: int  # ground-truth points evaluated

    def to_json(self) -> dict[str, Any]:
        """Plain dict; NaN becomes None."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


@dataclass(frozen=True)
class _PQ:
    pq: float
    sq: float
    rq: float
    per_class: dict[int, float]


def evaluate(
    pred_semantic: np.ndarray,  # (G,) int64, -1 void
    pred_instance: np.ndarray,  # (G,) int64, -1 none
    gt_semantic: np.ndarray,  # (G,) int64, -1 unannotated
    gt_instance: np.ndarray,  # (G,) int64, -1 none
    vocabulary: Vocabulary,
    *,
    mode: Literal["standard", "paper"] = "standard",
    iou_threshold: float = 0.25,
    ignore_classes: Sequence[str | int] = (),
) -> Metrics:
    """mIoU, mAcc, PRQ(T), PRQ(S) of one scene.

    Args:
        pred_semantic: Predicted class per ground-truth point. ``(G,)``.
        pred_instance: Predicted instance per point. ``(G,)``.
        gt_semantic: Ground-truth class per point. ``(G,)``.
        gt_instance: Ground-truth instance per point. ``(G,)``.
        vocabulary: Class names and kinds (indices of both label arrays).
        mode: ``standard`` or ``paper`` (see the module docstring).
        iou_threshold: Panoptic match threshold, strict ``>``.
        ignore_classes: Class names or indices left out of every average (their points still count).

    Raises:
        ShapeError: arrays of different lengths or not 1-D.
        InputError: labels outside ``[-1, L)``, unknown ignored class, unknown mode, threshold not in [0, 1).
    """
    ps, pi, gs, gi = _check_labels(
        pred_semantic, pred_instance, gt_semantic, gt_instance, num_classes=len(vocabulary.names)
    )
    if mode not in ("standard", "paper"):
        raise InputError(f"evaluate: mode must be 'standard' or 'paper', found {mode!r}")
    if not 0.0 <= iou_threshold < 1.0:
        raise InputError(f"evaluate: iou_threshold must be in [0, 1), found {iou_threshold}")
    excluded = _ignored(vocabulary, ignore_classes)
    num = len(vocabulary.names)
    points_of = _points_by_class(ps, gs, num)  # once for all the classes, thresholds and thing / stuff passes
    if mode == "paper":
        excluded |= {i for i, n in enumerate(vocabulary.names) if n.lower() in PAPER_EXCLUDED_NAMES}
        things, stuff = _paper_split(vocabulary, excluded)
        iou, acc, present = semantic_scores(ps, gs, num)
        pq = [
            _paper_pq(ps, pi, gs, gi, classes, t, points_of=points_of)
            for t in (iou_threshold, 0.5)
            for classes in (things, stuff)
        ]
        points = len(gs)
    else:
        annotated = gs >= 0
        iou, acc, present = semantic_scores(ps[annotated], gs[annotated], num)
        things = [c for c in range(num) if vocabulary.is_thing[c] and c not in excluded]
        stuff = [c for c in range(num) if not vocabulary.is_thing[c] and c not in excluded]
        pq = [
            _standard_pq(ps, pi, gs, gi, classes, t, thing=classes is things, points_of=points_of)
            for t in (iou_threshold, 0.5)
            for classes in (things, stuff)
        ]
        points = int(annotated.sum())
    valid = [c for c in range(num) if present[c] and c not in excluded]
    names = vocabulary.names
    return Metrics(
        mode=mode,
        iou_threshold=iou_threshold,
        miou=_mean(iou[valid]),
        macc=_mean(acc[valid]),
        prq_thing=pq[0].pq,
        prq_stuff=pq[1].pq,
        sq_thing=pq[0].sq,
        rq_thing=pq[0].rq,
        sq_stuff=pq[1].sq,
        rq_stuff=pq[1].rq,
        prq_thing_50=pq[2].pq,
        prq_stuff_50=pq[3].pq,
        class_iou={names[c]: float(iou[c]) for c in valid},
        class_acc={names[c]: float(acc[c]) for c in valid},
        class_pq={names[c]: v for part in pq[:2] for c, v in part.per_class.items()},
        num_points=points,
    )


def semantic_scores(pred: np.ndarray, gt: np.ndarray, num_classes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per class IoU, accuracy (recall) and presence in the ground truth; ``(L,)`` each.

    IoU_c = |pred=c and gt=c| / |pred=c or gt=c| (0 when the union is empty),
    Acc_c = |pred=c and gt=c| / |gt=c| (0 when no ground truth). Label -1 belongs to no class.

    Example:
        >>> iou, acc, present = semantic_scores(np.array([0, 0, 1]), np.array([0, 1, 1]), 2)
        >>> iou.tolist(), acc.tolist(), present.tolist()
        ([0.5, 0.5], [1.0, 0.5], [True, True])
    """
    both = (pred == gt) & (gt >= 0)
    inter = np.bincount(gt[both], minlength=num_classes).astype(np.float64)
    n_gt = np.bincount(gt[gt >= 0], minlength=num_classes).astype(np.float64)
    n_pred = np.bincount(pred[pred >= 0], minlength=num_classes).astype(np.float64)
    union = n_gt + n_pred - inter
    iou = np.divide(inter, union, out=np.zeros(num_classes), where=union > 0)
    acc = np.divide(inter, n_gt, out=np.zeros(num_classes), where=n_gt > 0)
    return iou, acc, n_gt > 0


def transfer_to_points(
    primitive_points: np.ndarray,  # (N, 3) float
    query_points: np.ndarray,  # (G, 3) float
    *values: np.ndarray,  # each (N, ...)
) -> tuple[np.ndarray, ...]:  # each (G, ...)
    """Give every query point the values of its nearest primitive (ground truth on other points).

    Raises:
        ShapeError: points not ``(., 3)``, no primitive, or a value array not ``N`` long.

    Example:
        >>> prim = np.array([[0.0, 0, 0], [1.0, 0, 0]])
        >>> transfer_to_points(prim, np.array([[0.9, 0, 0], [0.1, 0, 0]]), np.array([5, 7]))[0].tolist()
        [7, 5]
    """
    prim = np.asarray(primitive_points, np.float64)
    query = np.asarray(query_points, np.float64)
    if prim.ndim != 2 or prim.shape[1] != 3 or len(prim) == 0:
        raise ShapeError(f"primitive_points: expected (N, 3) with N >= 1, found {prim.shape}")
    if query.ndim != 2 or query.shape[1] != 3:
        raise ShapeError(f"query_points: expected (G, 3), found {query.shape}")
    for k, v in enumerate(values):
        if np.shape(v)[:1] != (len(prim),):
            raise ShapeError(f"values[{k}]: expected {len(prim)} rows (one per primitive), found {np.shape(v)}")
    _, nearest = cKDTree(prim).query(query, k=1, workers=1)
    return tuple(np.asarray(v)[nearest] for v in values)


def evaluate_ground_truth(
    primitive_points: np.ndarray,  # (N, 3) float
    pred_semantic: np.ndarray,  # (N,) int64, -1 void
    pred_instance: np.ndarray,  # (N,) int64, -1 none
    gt: GroundTruth,
    vocabulary: Vocabulary,
    *,
    modes: Sequence[Literal["standard", "paper"]] = ("standard", "paper"),
) -> dict[str, Metrics]:
    """Metrics of a per-primitive prediction against ground truth, one entry per mode.

    Ground truth with points takes the prediction of the nearest primitive (:func:`transfer_to_points`);
    ground truth without points is per primitive, in order.

    Args:
        primitive_points: Positions of the primitives. ``(N, 3)``.
        pred_semantic: Predicted class per primitive. ``(N,)``.
        pred_instance: Predicted instance per primitive. ``(N,)``.
        gt: Labels, with ``points`` ``(G, 3)`` or per primitive (``G == N``).
        vocabulary: The classes both label arrays index.
        modes: Evaluation modes to compute (see :func:`evaluate`).

    Raises:
        ShapeError: per-primitive ground truth whose length is not ``N``, or prediction arrays not ``N`` long.
        InputError: labels outside the vocabulary (see :func:`evaluate`).
    """
    pred_sem, pred_ins = np.asarray(pred_semantic), np.asarray(pred_instance)
    if gt.points is not None:
        pred_sem, pred_ins = transfer_to_points(primitive_points, gt.points, pred_sem, pred_ins)
    elif len(gt.semantic) != len(pred_sem):
        raise ShapeError(
            f"ground truth: {len(gt.semantic)} labels without points, expected one per primitive ({len(pred_sem)})"
        )
    return {mode: evaluate(pred_sem, pred_ins, gt.semantic, gt.instance, vocabulary, mode=mode) for mode in modes}


def _standard_pq(
    ps: np.ndarray,
    pi: np.ndarray,
    gs: np.ndarray,
    gi: np.ndarray,
    classes: list[int],
    threshold: float,
    *,
    thing: bool,
    points_of: list[np.ndarray] | None = None,
) -> _PQ:
    """Per-class PQ with per-class counters; see the module docstring.

    ``points_of[c]``: the points where ``gs`` or ``ps`` is ``c`` (:func:`_points_by_class`, computed when None).
    """
    if points_of is None:
        points_of = _points_by_class(ps, gs, max(classes, default=-1) + 1)
    void = gs < 0
    if thing:  # a thing point without a ground-truth instance cannot be matched: void for things
        void = void | ((gs >= 0) & (gi < 0))
    per_class: dict[int, float] = {}
    sq: list[float] = []
    rq: list[float] = []
    for c in classes:
        # Every other point is in no segment of class c on either side and drops out of every count below.
        at = points_of[c]
        c_gs, c_ps = gs[at], ps[at]
        if thing:
            g_ids, p_ids = np.where(c_gs == c, gi[at], -1), np.where(c_ps == c, pi[at], -1)
        else:  # stuff: one segment per class on each side
            g_ids, p_ids = np.where(c_gs == c, 0, -1), np.where(c_ps == c, 0, -1)
        tp, fp, fn, iou_sum = _match_class(g_ids, p_ids, void[at], threshold)
        if tp + fp + fn == 0:
            continue
        den = tp + 0.5 * fp + 0.5 * fn
        per_class[c] = iou_sum / den
        sq.append(iou_sum / tp if tp else 0.0)
        rq.append(tp / den)
    return _PQ(_mean(list(per_class.values())), _mean(sq), _mean(rq), per_class)


def _match_class(
    g_ids: np.ndarray, p_ids: np.ndarray, void: np.ndarray, threshold: float
) -> tuple[int, int, int, float]:
    """(TP, FP, FN, sum IoU of TP) of one class; ids -1 = not in a segment of this class."""
    g_mask, p_mask = (g_ids >= 0) & ~void, (p_ids >= 0) & ~void
    g_u, g_size = np.unique(g_ids[g_mask], return_counts=True)
    p_u, p_size = np.unique(p_ids[p_mask], return_counts=True)
    p_all_u, p_all_size = np.unique(p_ids[p_ids >= 0], return_counts=True)
    iou = _iou_matrix(g_ids, p_ids, g_mask & p_mask, g_u, g_size, p_u, p_size)
    pairs = np.argwhere(iou > threshold)
    order = np.argsort(-iou[pairs[:, 0], pairs[:, 1]], kind="stable")
    g_done, p_done = np.zeros(len(g_u), bool), np.zeros(len(p_u), bool)
    iou_sum = 0.0
    for gk, pk in pairs[order]:
        if not g_done[gk] and not p_done[pk]:
            g_done[gk] = p_done[pk] = True
            iou_sum += float(iou[gk, pk])
    # COCO: an unmatched prediction mostly on void is not a false positive (p_u is a subset of p_all_u).
    on_void = 1.0 - p_size / p_all_size[np.searchsorted(p_all_u, p_u)]
    fp = int(np.sum(~p_done & (on_void <= 0.5)))
    tp = int(g_done.sum())
    return tp, fp, len(g_u) - tp, iou_sum


def _iou_matrix(
    g_ids: np.ndarray,
    p_ids: np.ndarray,
    both: np.ndarray,
    g_u: np.ndarray,
    g_size: np.ndarray,
    p_u: np.ndarray,
    p_size: np.ndarray,
) -> np.ndarray:  # (len(g_u), len(p_u)) float64
    # Count the (gt, pred) pairs by their flat cell in the matrix: ids may be any int64, their ranks in g_u / p_u
    # are small, and a bincount of one int64 key is much cheaper than np.unique(axis=0) over rows.
    cell = np.searchsorted(g_u, g_ids[both]) * len(p_u) + np.searchsorted(p_u, p_ids[both])
    inter = np.bincount(cell, minlength=len(g_u) * len(p_u)).reshape(len(g_u), len(p_u)).astype(np.float64)
    union = g_size[:, None] + p_size[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def paper_class_match(
    ps: np.ndarray, pi: np.ndarray, gs: np.ndarray, gi: np.ndarray, c: int, threshold: float
) -> tuple[int, int, int, float]:  # TP, FP, FN, sum of matched IoUs
    """The reference's matching of one class (docs/method.md §8.2): each ground-truth instance, in ascending id
    order, takes the first unmatched prediction of highest IoU when it is over ``threshold``; -1 is a real id."""
    at = np.flatnonzero((gs == c) | (ps == c))
    return _paper_class_match(ps[at], pi[at], gs[at], gi[at], c, threshold)


def _paper_class_match(
    ps: np.ndarray, pi: np.ndarray, gs: np.ndarray, gi: np.ndarray, c: int, threshold: float
) -> tuple[int, int, int, float]:
    """:func:`paper_class_match` on any subset of the points that holds every point where ``gs`` or ``ps`` is
    ``c`` (the others are in no instance of class c and change no count)."""
    g_ids, p_ids = np.where(gs == c, gi, _NONE), np.where(ps == c, pi, _NONE)
    g_u, g_size = np.unique(g_ids[gs == c], return_counts=True)
    p_u, p_size = np.unique(p_ids[ps == c], return_counts=True)
    iou = _iou_matrix(g_ids, p_ids, (gs == c) & (ps == c), g_u, g_size, p_u, p_size)
    tp = fn = 0
    iou_sum = 0.0
    remaining = np.ones(len(p_u), bool)
    for row in iou:
        masked = np.where(remaining, row, -1.0)
        best = int(np.argmax(masked)) if len(masked) else -1  # first of the highest: strict > in a loop
        if best >= 0 and masked[best] > threshold:
            tp += 1
            iou_sum += float(masked[best])
            remaining[best] = False
        else:
            fn += 1
    return tp, int(remaining.sum()), fn, iou_sum


def _paper_pq(
    ps: np.ndarray,
    pi: np.ndarray,
    gs: np.ndarray,
    gi: np.ndarray,
    classes: list[int],
    threshold: float,
    *,
    points_of: list[np.ndarray],
) -> _PQ:
    """The reference's ``panoptic()`` (docs/method.md §8.2), quirks included (cumulative TP / FN / IoU sum,
    per-class FP). ``points_of[c]``: the points where ``gs`` or ``ps`` is ``c`` (:func:`_points_by_class`)."""
    tp = fn = n_valid = 0
    iou_sum = pq = sq = rq = 0.0
    per_class: dict[int, float] = {}
    for c in classes:
        at = points_of[c]
        c_tp, fp, c_fn, c_iou = _paper_class_match(ps[at], pi[at], gs[at], gi[at], c, threshold)
        tp, fn, iou_sum = tp + c_tp, fn + c_fn, iou_sum + c_iou  # cumulative over classes: the reference's quirk
        den = tp + 0.5 * fp + 0.5 * fn
        if tp + fp + fn > 0:
            per_class[c] = iou_sum / den
            pq += iou_sum / den
            rq += tp / den
            n_valid += 1
        if tp > 0:
            sq += iou_sum / tp
    if n_valid == 0:  # the reference divides by zero here
        return _PQ(math.nan, math.nan, math.nan, per_class)
    return _PQ(pq / n_valid, sq / n_valid, rq / n_valid, per_class)


def _points_by_class(ps: np.ndarray, gs: np.ndarray, num_classes: int) -> list[np.ndarray]:
    """Per class ``c < num_classes``, the indices of the points where the prediction or the ground truth is c.

    One sort per side instead of full-length masks per class: each class's matching then touches only its own
    points, which is all it counts. The order within a class is arbitrary (only counts are taken from it).
    """
    bounds = np.arange(num_classes + 1)
    g_order, p_order = np.argsort(gs), np.argsort(ps)
    g_at, p_at = np.searchsorted(gs[g_order], bounds), np.searchsorted(ps[p_order], bounds)
    out = []
    for c in range(num_classes):
        g_c, p_c = g_order[g_at[c] : g_at[c + 1]], p_order[p_at[c] : p_at[c + 1]]
        out.append(np.concatenate([g_c, p_c[gs[p_c] != c]]))  # a point of class c on both sides, once
    return out


_NONE = np.iinfo(np.int64).min  # "not in this class" in _paper_pq, where -1 is a real instance id


def _paper_split(vocabulary: Vocabulary, excluded: set[int]) -> tuple[list[int], list[int]]:
    split = None
    for key, (names, _) in BUILTIN_VOCABULARIES.items():
        if tuple(n.lower() for n in vocabulary.names) == names:
            split = PAPER_SPLITS[key]
    if split is None:
        thing_flags = vocabulary.is_thing
        split = (tuple(np.flatnonzero(thing_flags)), tuple(np.flatnonzero(~thing_flags)))
    return ([int(c) for c in split[0] if c not in excluded], [int(c) for c in split[1] if c not in excluded])


def _ignored(vocabulary: Vocabulary, ignore: Sequence[str | int]) -> set[int]:
    lowered = [n.lower() for n in vocabulary.names]
    out: set[int] = set()
    for item in ignore:
        if isinstance(item, str) and item.lower() in lowered:
            out.add(lowered.index(item.lower()))
        elif isinstance(item, int | np.integer) and 0 <= int(item) < len(lowered):
            out.add(int(item))
        else:
            raise InputError(f"ignore_classes: {item!r} is not a class of the vocabulary")
    return out


def _check_labels(*arrays: np.ndarray, num_classes: int) -> tuple[np.ndarray, ...]:
    names = ("pred_semantic", "pred_instance", "gt_semantic", "gt_instance")
    out = tuple(np.asarray(a) for a in arrays)
    for name, a in zip(names, out):
        if a.ndim != 1 or a.shape != out[2].shape:
            raise ShapeError(f"{name}: expected 1-D of the ground truth's length {out[2].shape}, found {a.shape}")
        # Integer arrays hold integers: the full-length np.mod pass is only for floats.
        if len(a) and a.dtype.kind not in "iu" and not np.all(np.equal(np.mod(a, 1), 0)):
            raise InputError(f"{name}: expected integer labels")
    out = tuple(a.astype(np.int64) for a in out)
    for name, a in ((names[0], out[0]), (names[2], out[2])):
        if len(a) and (a.min() < -1 or a.max() >= num_classes):
            raise InputError(f"{name}: class ids must be in [-1, {num_classes}), found [{a.min()}, {a.max()}]")
    return out


def _mean(values: Any) -> float:
    values = np.asarray(values, np.float64)
    return float(values.mean()) if values.size else math.nan


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, float) and math.isnan(value):
        return None
    return value
