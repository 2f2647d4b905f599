"""The class of each primitive: its evidence (fused and field cosines), then the votes inside super-primitives
(docs/method.md §7.2-7.3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from panogs_core.stages.labeling.config import LabelingConfig


@dataclass(frozen=True)
class FusedEvidence:
    """What the labelling reads of the fused features: their cosines with the classes and which rows were seen.

    ``(N, L)`` instead of the ``(N, D)`` features (161 MB at ScanNet size): the pipeline makes it once the field is
    fitted and drops the fused features, so the later stages never hold them beside the decoded ones.
    """

    cosines: np.ndarray  # (N, L) float32, cos(F, e) of the fused mean F with each unit class embedding; 0 unseen
    seen: np.ndarray  # (N,) bool, some key frame saw the primitive (its fused mean is not zero)

    @classmethod
    def of(cls, fused: np.ndarray, emb: np.ndarray) -> FusedEvidence:
        """From the ``(N, D)`` fused mean features (zero rows where unseen) and the ``(L, D)`` unit embeddings."""
        sq_norm = np.einsum("nd,nd->n", fused, fused)  # (N,) no normalised (N, D) copy (0.3 GB at 150k)
        cosines = (fused @ emb.T) / np.maximum(np.sqrt(sq_norm), 1e-12)[:, None]
        return cls(cosines=cosines, seen=sq_norm > 1e-12)


def primitive_classes(
    field_sims: np.ndarray,  # (N, L) cosines of the field features with the class embeddings
    fused: FusedEvidence,  # the fused features' cosines, and the primitives some key frame saw
    cfg: LabelingConfig,
) -> tuple[np.ndarray, np.ndarray]:  # (N,) int64 class (-1 where unseen), (N, L) the scores
    """Class of each seen primitive from its fused and field cosines; -1 where no key frame saw it.

    DEPARTURE (half fused, half field, not the field alone; docs/method.md §7.5): the field smooths small classes
    into the large ones beside them. ``evidence_fused_weight`` mixes the two cosines (1 = fused only).
    """
    w = cfg.evidence_fused_weight
    seen = fused.seen
    scores = field_sims * (1.0 - w) if w < 1.0 else np.zeros_like(field_sims)
    if w > 0.0:
        scores[seen] += w * fused.cosines[seen]
    return np.where(seen, np.argmax(scores, axis=1), -1).astype(np.int64), scores


def vote_islands(
    classes: np.ndarray,  # (N,) int64 in [-1, L)
    segments: np.ndarray,  # (N,) int64 >= 0
    neighbors: np.ndarray,  # (N, K) kNN (self excluded)
    island_points: int,
    min_fraction: float = 0.5,
    scores: np.ndarray | None = None,  # (N, L) class scores the classes are the argmax of
    max_margin: float | None = None,
) -> np.ndarray:  # (N,) int64
    """The vote inside super-primitives, restricted to small islands of another class.

    A primitive takes its segment's majority class only when it belongs to a connected patch (over the kNN
    graph, inside the segment) of its own class smaller than ``island_points`` primitives, and the majority
    holds at least ``min_fraction`` of the segment's classified primitives. A large patch of another class
    inside a segment is kept: it is an object on or in a larger one (a counter top on the cabinets under it, a
    picture in its wall), which the graph cut could not separate, not noise. Unclassified primitives (-1) are
    left to :func:`label_unseen`.

    Example:
        >>> nbr = np.array([[1], [0], [1], [2], [3]])
        >>> vote_islands(np.array([1, 1, 2, 1, 1]), np.zeros(5, np.int64), nbr, island_points=2).tolist()
        [1, 1, 1, 1, 1]
    """
    voters = classes >= 0
    if not voters.any():
        return classes.copy()
    seg, major, count, total = majority(segments[voters], classes[voters])
    winner = np.full(int(segments.max()) + 1, -1, np.int64)
    keep = count >= min_fraction * total
    winner[seg[keep]] = major[keep]
    n = classes.size
    src = np.repeat(np.arange(n), neighbors.shape[1])
    dst = neighbors.reshape(-1)
    same = voters[src] & (classes[src] == classes[dst]) & (segments[src] == segments[dst])
    graph = sparse.csr_matrix((np.ones(int(same.sum()), np.int8), (src[same], dst[same])), shape=(n, n))
    _, patch = csgraph.connected_components(graph, directed=False)
    small = np.bincount(patch, minlength=n)[patch] < island_points
    target = winner[segments]
    flip = voters & small & (target >= 0) & (target != classes)
    if scores is not None and max_margin is not None:
        # Only where the segment's class is a close second: its score trails the primitive's own by at most
        # ``max_margin``. A confident island (a sink the masks and features agree on) keeps its class.
        rows = np.flatnonzero(flip)
        gap = scores[rows, classes[rows]] - scores[rows, target[rows]]
        flip[rows[gap > max_margin]] = False
    out = classes.copy()
    out[flip] = target[flip]
    return out


def vote_in_segments(
    classes: np.ndarray,  # (N,) int64 in [-1, L)
    segments: np.ndarray,  # (N,) int64 >= 0
    min_fraction: float = 0.0,
) -> np.ndarray:  # (N,) int64
    """Replace the class of every point of a segment by the segment's majority class.

    Points of class -1 do not vote but receive the vote. Ties go to the smallest class (scipy.stats.mode, as
    in the reference). A segment is voted only when its majority holds ``>= min_fraction`` of its voters.

    Example:
        >>> vote_in_segments(np.array([1, 1, 2, 3, -1]), np.array([0, 0, 0, 1, 1])).tolist()
        [1, 1, 1, 3, 3]
    """
    voters = classes >= 0
    if not voters.any():
        return classes.copy()
    seg, major, count, total = majority(segments[voters], classes[voters])
    keep = count >= min_fraction * total
    winner = np.full(int(segments.max()) + 1, -1, np.int64)
    winner[seg[keep]] = major[keep]
    voted = winner[segments]
    return np.where(voted >= 0, voted, classes)


def majority(groups: np.ndarray, classes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per group present: (group id, majority class, its count, group size); ties -> smallest class."""
    span = int(classes.max()) + 1
    keys, counts = np.unique(groups * span + classes, return_counts=True)
    grp, cls = keys // span, keys % span
    order = np.lexsort((cls, -counts, grp))  # per group: most votes first, then smallest class
    first = order[np.r_[True, grp[order][1:] != grp[order][:-1]]]
    totals = np.bincount(grp, weights=counts).astype(np.int64)
    return grp[first], cls[first], counts[first], totals[grp[first]]
