"""Stage 6: multi-view mask affinity between adjacent segments (docs/method.md §5).

Inputs: the scene's 2D instance masks, the visibility of stage 2, a segment id per primitive (the
super-primitives, or the clusters of an earlier clustering round) and the primitive kNN graph. Output: one
affinity per pair of segments, in ``[1 - ln 2, 1]`` where the two are seen together in some mask frame and 0
where they never are.

For a mask frame m and a segment i, let ``p_i^m`` be the distribution of the mask ids of i's members that m
sees inside a mask, and ``r_i^m`` the fraction of i's members that m sees inside a mask (visibility ratio):

    A_ij = sum_m (1 - JSD(p_i^m, p_j^m)) r_i^m r_j^m / sum_m r_i^m r_j^m,    JSD in nats.

Everything is sparse: the histograms are (segment, frame, mask id) entries with a count, built with one sort,
and a pair is joined only on the frames where both segments have entries and only on their common mask ids,
all with ``searchsorted`` on sorted int64 keys. Memory is bounded by joining pairs in chunks of (pair, frame)
rows.

Example:
    >>> import numpy as np
    >>> obs = MaskObservations(offsets=np.array([0, 4]), point_index=np.arange(4, dtype=np.int32),
    ...                        label=np.array([3, 3, 3, 5], dtype=np.int32))
    >>> labels = np.array([0, 0, 1, 1])  # segment 1 is half in mask 3, half in mask 5
    >>> edge_affinity(labels, np.array([[0, 1]]), obs, AffinityConfig()).round(4)
    array([0.7842], dtype=float32)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from scipy import sparse

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.stages.masks import MaskLookupConfig, MaskObservations

if TYPE_CHECKING:
    from panogs_core.stages.neighbors import KnnGraph

LN2 = math.log(2.0)
_KEY_LIMIT = 1 << 62  # largest (segment, frame, mask id) key space that fits an int64 with room to spare


@dataclass(frozen=True, kw_only=True)
class AffinityConfig:
    """Settings of the edge affinity (stage 6).

    Attributes:
        mode: ``"jsd"``: mask-label Jensen-Shannon similarity (the paper). ``"language"``: the ablation that
            uses the cosine of the segments' mean language features instead, and ignores the masks.
        min_covisibility: Pairs whose co-visibility weight ``sum_m r_i r_j`` (unit: frames) is not above this
            get affinity 0, as if never seen together. 0 reproduces the reference (docs/method.md §5.4: ``C_ij != 0``).
        eps: Floor of the norm of a mean language feature before normalising (mode ``"language"``).
        chunk_rows: (pair, frame) rows joined at once; bounds memory (about 100 bytes a row), not the result.
        mask_depth_mad: A seen primitive reads its mask id only if its relative depth residual is within this
            many robust standard deviations (1.4826 MAD) of the frame's median residual; 0 turns it off.
        mask_depth_floor: The smallest tolerance of that test, relative depth.
        aggregate: How the per-frame similarities of a pair are combined, both weighted by ``r_i r_j``:
            ``"mean"`` (the paper and reference) or ``"median"``.
    """

    mode: Literal["jsd", "language"] = "jsd"
    min_covisibility: float = 0.0
    eps: float = 1e-8
    chunk_rows: int = 2_000_000
    # Option, off by default (docs/method.md §5.1: the reference reads masks with the visibility test, rtol 0.07): 7 %
    # of depth is 20 cm at 3 m, so a surface hidden a few centimetres behind another (the inside of a bookshelf behind
    # its neighbour's side) passes and reads the mask of the object in front. The residuals of one frame are mostly true
    # surfaces, so their spread measures that frame's depth noise: with mask_depth_mad = 3, observations off by more
    # than 3 spreads are left out of the mask lookups (fusion keeps the reference's test). On a synthetic easy room true
    # residuals spread +-1 % and leaked ones sat at 3-6 %, yet the quality bench measured no gain (docs/benchmarks.md,
    # "depth-filter"), so it stays off.
    mask_depth_mad: float = 0.0
    mask_depth_floor: float = 0.01
    # DEPARTURE (docs/method.md §5.4): "median" is the weighted median over views, where the reference averages; it
    # follows the majority of views past SAM's per-frame merges and splits.
    aggregate: Literal["mean", "median"] = "median"

    def __post_init__(self) -> None:
        if self.aggregate not in ("mean", "median"):
            raise ConfigError(f"affinity.aggregate: expected 'mean' or 'median', found {self.aggregate!r}")
        if self.mode not in ("jsd", "language"):
            raise ConfigError(f"affinity.mode: expected 'jsd' or 'language', found {self.mode!r}")
        if not math.isfinite(self.min_covisibility) or self.min_covisibility < 0:
            raise ConfigError(f"affinity.min_covisibility: expected a number >= 0, found {self.min_covisibility}")
        if not math.isfinite(self.eps) or self.eps <= 0:
            raise ConfigError(f"affinity.eps: expected a number > 0, found {self.eps}")
        if not math.isfinite(self.mask_depth_mad) or self.mask_depth_mad < 0:
            raise ConfigError(f"affinity.mask_depth_mad: expected a number >= 0, found {self.mask_depth_mad}")
        if not math.isfinite(self.mask_depth_floor) or self.mask_depth_floor <= 0:
            raise ConfigError(f"affinity.mask_depth_floor: expected a number > 0, found {self.mask_depth_floor}")
        if isinstance(self.chunk_rows, bool) or not isinstance(self.chunk_rows, int) or self.chunk_rows < 1:
            raise ConfigError(f"affinity.chunk_rows: expected an integer >= 1, found {self.chunk_rows!r}")

    def mask_lookup(self) -> MaskLookupConfig:
        """The two settings the mask look-ups read (they live in this YAML section since before that stage)."""
        return MaskLookupConfig(depth_mad=self.mask_depth_mad, depth_floor=self.mask_depth_floor)


def segment_adjacency(
    labels: np.ndarray,  # (N,) int64, segment per primitive, -1 = none
    knn: KnnGraph,
) -> tuple[np.ndarray, np.ndarray]:  # (E, 2) int64, (E,) int64
    """Adjacent segment pairs, with the number of primitive kNN edges that join them.

    Two segments are adjacent when a primitive of one has a primitive of the other among its k nearest
    neighbours (docs/method.md §5.2, direct adjacency). Primitives labelled -1 and neighbour slots -1 are ignored.

    Args:
        labels: Segment id per primitive. ``(N,)``.
        knn: Primitive kNN graph; ``neighbors`` is ``(N, K)`` int64, self excluded.

    Returns:
        ``pairs`` ``(E, 2)`` int64, unique, ``pairs[:, 0] < pairs[:, 1]``, ascending; and ``edges`` ``(E,)``
        int64, the directed kNN edges between the two segments (an edge listed both ways counts twice).

    Raises:
        ShapeError: if ``labels`` and ``knn.neighbors`` disagree on N.
    """
    labels = _as_labels(labels, "segment_adjacency")
    neighbors = np.asarray(knn.neighbors, dtype=np.int64)
    if neighbors.ndim != 2 or neighbors.shape[0] != labels.size:
        raise ShapeError(
            f"segment_adjacency: knn.neighbors must be ({labels.size}, K) to match labels, found {neighbors.shape}"
        )
    src = np.broadcast_to(labels[:, None], neighbors.shape)
    dst = np.where(neighbors >= 0, labels[np.maximum(neighbors, 0)], -1)
    keep = (src != dst) & (src >= 0) & (dst >= 0)
    lo = np.minimum(src[keep], dst[keep])
    hi = np.maximum(src[keep], dst[keep])
    span = int(labels.max()) + 1 if labels.size else 1
    keys, edges = np.unique(lo * span + hi, return_counts=True)
    return np.stack([keys // span, keys % span], axis=1), edges.astype(np.int64)


def edge_affinity(
    labels: np.ndarray,  # (N,) int64, segment per primitive, -1 = none
    pairs: np.ndarray,  # (E, 2) int64, segment ids
    observations: MaskObservations,
    cfg: AffinityConfig,
    *,
    features: np.ndarray | None = None,  # (N, D) float32, unit rows; mode "language" only
) -> np.ndarray:  # (E,) float32
    """Affinity of each segment pair (docs/method.md §5.3-5.4; see the module docstring for the formula).

    Symmetric by construction: the same value for ``(i, j)`` and ``(j, i)``.

    Args:
        labels: Segment id per primitive. ``(N,)``.
        pairs: Segment pairs, any order within a row. ``(E, 2)``.
        observations: Mask ids under the primitives, per mask frame (:func:`observe_masks`).
        cfg: Mode and limits.
        features: Per-primitive language features; required by mode ``"language"``. ``(N, D)``.

    Returns:
        ``(E,)`` float32. Mode ``"jsd"``: in ``[1 - ln 2, 1]``, 0 for pairs never seen together. Mode
        ``"language"``: cosine of the segments' mean features, in ``[-1, 1]``.

    Raises:
        InputError: if mode ``"language"`` has no ``features``, or a pair names a segment no primitive has.
        ShapeError: if an array has the wrong shape.
    """
    labels = _as_labels(labels, "edge_affinity")
    pairs = _check_pairs(pairs, int(labels.max()) + 1 if labels.size else 0)
    if cfg.mode == "language":
        return _language_affinity(labels, pairs, features, cfg)
    return MaskHistograms.build(labels, observations).affinity(pairs, cfg)


SegmentAffinity = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (segment of each sp (S0,), pairs (E, 2)) -> (E,)


def segment_affinity(
    sp_labels: np.ndarray,  # (N,) int64, super-primitive per primitive, -1 = none
    observations: MaskObservations,
    cfg: AffinityConfig,
    *,
    features: np.ndarray | None = None,  # (N, D) float32, unit rows; mode "language" only
) -> SegmentAffinity:
    """The affinity of pairs of merged segments, given the segment each super-primitive belongs to.

    The clustering of stage 7 merges super-primitives round after round and measures its segments again each
    round (docs/method.md §6); this is that measure, with every affinity setting bound, so the clustering needs
    no affinity settings of its own.

    Returns:
        ``affinity(segment_of_sp, pairs)``: ``segment_of_sp`` ``(S0,)`` int64 maps super-primitive ids to
        segment ids; ``pairs`` ``(E, 2)`` int64 names segments; the result is ``(E,)`` as :func:`edge_affinity`.
    """
    sp_labels = _as_labels(sp_labels, "segment_affinity")
    if cfg.mode == "language":

        def language(segment_of_sp: np.ndarray, pairs: np.ndarray) -> np.ndarray:
            labels = np.where(sp_labels >= 0, segment_of_sp[np.maximum(sp_labels, 0)], -1)
            return edge_affinity(labels, pairs, observations, cfg, features=features)

        return language
    # The mask histograms of merged segments are the sums of their super-primitives' histograms: build those
    # once from the T observations, then each round only re-keys the far smaller (segment, frame, id) table.
    base = MaskHistograms.build(sp_labels, observations)

    def jsd(segment_of_sp: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        return base.coarsen(segment_of_sp).affinity(pairs, cfg)

    return jsd


def _as_labels(labels: np.ndarray, where: str) -> np.ndarray:  # (N,) int64
    labels = np.asarray(labels)
    if labels.ndim != 1 or not np.issubdtype(labels.dtype, np.integer):
        raise ShapeError(f"{where}: labels must be (N,) integers, found {labels.shape} {labels.dtype}")
    return labels.astype(np.int64, copy=False)


def _check_pairs(pairs: np.ndarray, num_segments: int) -> np.ndarray:  # (E, 2) int64
    pairs = np.asarray(pairs)
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
        raise ShapeError(f"edge_affinity: pairs must be (E, 2) integers, found {pairs.shape} {pairs.dtype}")
    if pairs.min() < 0 or pairs.max() >= num_segments:
        raise InputError(
            f"edge_affinity: pairs name segments in [{pairs.min()}, {pairs.max()}], labels have [0, {num_segments})"
        )
    return pairs.astype(np.int64, copy=False)


def _language_affinity(
    labels: np.ndarray,  # (N,) int64
    pairs: np.ndarray,  # (E, 2) int64
    features: np.ndarray | None,  # (N, D)
    cfg: AffinityConfig,
) -> np.ndarray:  # (E,) float32
    # Ablation (not the paper's affinity): how alike two segments' language is, ignoring the masks.
    if features is None:
        raise InputError("edge_affinity: mode 'language' needs features (N, D); none were given")
    features = np.asarray(features, dtype=np.float32)
    if features.ndim != 2 or features.shape[0] != labels.size:
        raise ShapeError(f"edge_affinity: features must be ({labels.size}, D), found {features.shape}")
    valid = np.flatnonzero(labels >= 0)
    num_segments = int(labels.max()) + 1 if labels.size else 0
    member = sparse.csr_matrix(
        (np.ones(valid.size, dtype=np.float32), (labels[valid], valid)), shape=(num_segments, labels.size)
    )
    means = np.asarray(member @ features, dtype=np.float64)  # (S, D); sums, the direction is all that matters
    means /= np.maximum(np.linalg.norm(means, axis=1, keepdims=True), cfg.eps)
    cosine = np.einsum("ed,ed->e", means[pairs[:, 0]], means[pairs[:, 1]])
    return cosine.astype(np.float32)


def _ragged_arange(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:  # (sum(lengths),) int64
    """Concatenation of ``arange(starts[k], starts[k] + lengths[k])`` over k, without a loop."""
    lengths = lengths.astype(np.int64, copy=False)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    before = np.cumsum(lengths) - lengths  # position of each run's first element in the output
    return np.repeat(starts.astype(np.int64) - before, lengths) + np.arange(total, dtype=np.int64)


def _lookup(sorted_keys: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of ``queries`` in ``sorted_keys`` and whether each was found."""
    if sorted_keys.size == 0:
        return np.zeros(queries.size, dtype=np.int64), np.zeros(queries.size, dtype=bool)
    at = np.minimum(np.searchsorted(sorted_keys, queries), sorted_keys.size - 1)
    return at, sorted_keys[at] == queries


@dataclass(frozen=True)
class MaskHistograms:
    """Sparse per (segment, mask frame) histograms of mask ids, the input of the JSD affinity.

    Entries are keyed ``key = (segment * V + frame) * L + mask_id`` (ascending); the entries of one (segment,
    frame) form a contiguous *group*, and the groups of one segment are contiguous too. Built once from the
    primitives, the histograms of merged segments follow by :meth:`coarsen` without touching the primitives.

    Attributes:
        num_frames: V.
        label_span: L, every mask id is below it.
        segment_size: Members per segment, seen or not. ``(S,)`` int64.
        entry_key: ``(X,)`` int64, ascending. entry_count: ``(X,)`` int64. entry_prob: ``(X,)`` float64, the
            count over its group's total.
        group_start: ``(G + 1,)`` int64, group g owns entries ``group_start[g]:group_start[g + 1]``.
        group_key: ``(G,)`` int64 ``segment * V + frame``, ascending. group_ratio: ``(G,)`` float64, r.
        segment_start: ``(S + 1,)`` int64, segment i owns groups ``segment_start[i]:segment_start[i + 1]``.
    """

    num_frames: int
    label_span: int
    segment_size: np.ndarray
    entry_key: np.ndarray
    entry_count: np.ndarray
    entry_prob: np.ndarray
    group_start: np.ndarray
    group_key: np.ndarray
    group_ratio: np.ndarray
    segment_start: np.ndarray

    @property
    def num_segments(self) -> int:
        """S."""
        return int(self.segment_size.size)

    @classmethod
    def build(cls, labels: np.ndarray, observations: MaskObservations) -> MaskHistograms:
        """Histograms of the segments ``labels`` (``(N,)`` int64, -1 = none) over the observed mask ids."""
        labels = _as_labels(labels, "MaskHistograms")
        num_frames = observations.num_frames
        index = observations.point_index.astype(np.int64)
        if index.size and (index.min() < 0 or index.max() >= labels.size):
            raise InputError(f"edge_affinity: observations name primitives outside [0, {labels.size})")
        frame = np.repeat(np.arange(num_frames, dtype=np.int64), np.diff(observations.offsets))
        segment = labels[index]
        mask_id = observations.label.astype(np.int64)
        keep = (segment >= 0) & (mask_id > 0)
        segment, frame, mask_id = segment[keep], frame[keep], mask_id[keep]
        num_segments = int(labels.max()) + 1 if labels.size else 0
        span = int(mask_id.max()) + 1 if mask_id.size else 1
        if num_segments * max(num_frames, 1) * span >= _KEY_LIMIT:
            # Ids only need to be told apart within a frame; renumbering them densely keeps the keys in int64.
            mask_id = np.unique(mask_id, return_inverse=True)[1].reshape(-1) + 1
            span = int(mask_id.max()) + 1
        keys, counts = np.unique((segment * num_frames + frame) * span + mask_id, return_counts=True)
        size = np.bincount(labels[labels >= 0], minlength=num_segments)
        return cls._from_entries(num_frames, span, size, keys, counts)

    def coarsen(self, segment_map: np.ndarray) -> MaskHistograms:
        """Histograms after merging segments: segment i becomes ``segment_map[i]`` (``(S,)`` int64, >= 0)."""
        segment_map = np.asarray(segment_map, dtype=np.int64)
        num_segments = int(segment_map.max()) + 1 if segment_map.size else 0
        block = self.num_frames * self.label_span  # key = segment * block + (frame * L + mask id)
        merged = segment_map[self.entry_key // block] * block + self.entry_key % block
        keys, inverse = np.unique(merged, return_inverse=True)
        counts = np.bincount(inverse.reshape(-1), weights=self.entry_count, minlength=keys.size)
        size = np.bincount(segment_map, weights=self.segment_size, minlength=num_segments)
        return self._from_entries(
            self.num_frames, self.label_span, size.astype(np.int64), keys, counts.astype(np.int64)
        )

    @classmethod
    def _from_entries(
        cls,
        num_frames: int,
        span: int,
        segment_size: np.ndarray,  # (S,) int64
        keys: np.ndarray,  # (X,) int64 ascending, unique
        counts: np.ndarray,  # (X,) int64
    ) -> MaskHistograms:
        group_of_entry = keys // span
        first = np.flatnonzero(np.diff(group_of_entry, prepend=-1)) if keys.size else np.zeros(0, np.int64)
        group_start = np.append(first, keys.size).astype(np.int64)
        group_key = group_of_entry[first]
        total = np.add.reduceat(counts, first) if keys.size else np.zeros(0, np.int64)  # (G,) seen in a mask
        segment_of_group = group_key // max(num_frames, 1)
        bounds = np.arange(segment_size.size + 1, dtype=np.int64) * num_frames
        return cls(
            num_frames=num_frames,
            label_span=span,
            segment_size=segment_size,
            entry_key=keys,
            entry_count=counts,
            entry_prob=counts / np.repeat(total, np.diff(group_start)).astype(np.float64),
            group_start=group_start,
            group_key=group_key,
            group_ratio=total / segment_size[segment_of_group].astype(np.float64),
            segment_start=np.searchsorted(group_key, bounds).astype(np.int64),
        )

    def affinity(self, pairs: np.ndarray, cfg: AffinityConfig) -> np.ndarray:  # (E,) float32
        """JSD affinity of segment ``pairs`` (``(E, 2)`` int64, any order in a row); see the module doc."""
        # DEPARTURE (pairs, docs/method.md §5.4, pitfall 16): only the requested pairs, symmetric by construction;
        # the reference fills dense blocks of 200 ids and symmetrises them by max.
        pairs = _check_pairs(pairs, self.num_segments)
        groups = np.diff(self.segment_start)
        # Expand each pair over the frames of whichever segment is seen in fewer: fewer rows, same answer.
        flip = groups[pairs[:, 0]] > groups[pairs[:, 1]]
        a = np.where(flip, pairs[:, 1], pairs[:, 0])
        b = np.where(flip, pairs[:, 0], pairs[:, 1])
        rows = groups[a]
        out = np.zeros(pairs.shape[0], dtype=np.float64)
        for lo, hi in _chunks(rows, cfg.chunk_rows):
            out[lo:hi] = self._affinity_chunk(a[lo:hi], b[lo:hi], rows[lo:hi], cfg)
        return out.astype(np.float32)

    def _affinity_chunk(
        self, a: np.ndarray, b: np.ndarray, rows: np.ndarray, cfg: AffinityConfig
    ) -> np.ndarray:  # (E_chunk,) float64
        pair_row, group_a, group_b = self._co_observed(a, b, rows)
        similarity = 1.0 - self._jsd(group_a, group_b)  # (R,) per (pair, frame)
        weight = self.group_ratio[group_a] * self.group_ratio[group_b]  # c = r_i r_j
        den = np.bincount(pair_row, weights=weight, minlength=a.size)
        seen = den > cfg.min_covisibility
        if cfg.aggregate == "median":
            value = weighted_median(pair_row, similarity, weight, a.size)
        else:
            value = np.bincount(pair_row, weights=similarity * weight, minlength=a.size) / np.where(seen, den, 1.0)
        return np.where(seen, value, 0.0)

    def _co_observed(
        self, a: np.ndarray, b: np.ndarray, rows: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # (R,) pair row, (R,) group of a, (R,) group of b
        """The (pair, frame) rows where both segments of a pair have a histogram."""
        pair_row = np.repeat(np.arange(a.size, dtype=np.int64), rows)
        group_a = _ragged_arange(self.segment_start[a], rows)
        frame = self.group_key[group_a] % self.num_frames
        group_b, found = _lookup(self.group_key, b[pair_row] * self.num_frames + frame)
        return pair_row[found], group_a[found], group_b[found]

    def _jsd(self, group_a: np.ndarray, group_b: np.ndarray) -> np.ndarray:  # (R,) float64 in [0, ln 2]
        """Jensen-Shannon divergence (nats) between the distributions of two groups, row by row.

        With m = (p + q) / 2, JSD = 1/2 KL(p || m) + 1/2 KL(q || m). A label that only p has contributes
        p ln(p / (p / 2)) = p ln 2, so all labels outside the common support together add
        1/2 ln 2 [(1 - sum_common p) + (1 - sum_common q)], and only the common labels need a join:
        JSD = 1/2 sum_common [p ln(2p / (p + q)) + q ln(2q / (p + q))] + 1/2 ln 2 (2 - P_c - Q_c).
        """
        # DEPARTURE (distributions, docs/method.md §5.3): true distributions in nats, not the reference's
        # L2-normalised counts: 1 - JSD lies in [1 - ln 2, 1], exact over the supports, with no eps.
        size = self.group_start[1:] - self.group_start[:-1]
        # Most (segment, frame) histograms hold a single mask id; two of them need no join: 0 or ln 2.
        single = (size[group_a] == 1) & (size[group_b] == 1)
        id_a = self.entry_key[self.group_start[group_a[single]]] % self.label_span
        id_b = self.entry_key[self.group_start[group_b[single]]] % self.label_span
        jsd = np.zeros(group_a.size, dtype=np.float64)
        jsd[single] = np.where(id_a == id_b, 0.0, LN2)
        mixed = ~single
        jsd[mixed] = self._jsd_joined(group_a[mixed], group_b[mixed], size)
        return jsd

    def _jsd_joined(
        self,
        group_a: np.ndarray,  # (R,) int64
        group_b: np.ndarray,  # (R,) int64
        size: np.ndarray,  # (G,) int64, entries per group
    ) -> np.ndarray:  # (R,) float64 in [0, ln 2]
        """:meth:`_jsd` by joining the two histograms on their common mask ids."""
        flip = size[group_a] > size[group_b]  # walk the smaller histogram, look labels up in the larger
        x = np.where(flip, group_b, group_a)
        y = np.where(flip, group_a, group_b)
        row = np.repeat(np.arange(x.size, dtype=np.int64), size[x])
        entry_x = _ragged_arange(self.group_start[x], size[x])
        mask_id = self.entry_key[entry_x] % self.label_span
        entry_y, common = _lookup(self.entry_key, self.group_key[y][row] * self.label_span + mask_id)
        row = row[common]
        p = self.entry_prob[entry_x[common]]
        q = self.entry_prob[entry_y[common]]
        mix = p + q
        inside = p * np.log(2.0 * p / mix) + q * np.log(2.0 * q / mix)
        p_common = np.bincount(row, weights=p, minlength=x.size)
        q_common = np.bincount(row, weights=q, minlength=x.size)
        outside = 2.0 - p_common - q_common  # mass of each side on labels the other side lacks
        jsd = 0.5 * np.bincount(row, weights=inside, minlength=x.size) + 0.5 * LN2 * outside
        return np.clip(jsd, 0.0, LN2)  # rounding only


def weighted_median(
    group: np.ndarray,  # (R,) int64 group of each value, in [0, G)
    values: np.ndarray,  # (R,) float64
    weights: np.ndarray,  # (R,) float64, >= 0
    num_groups: int,
) -> np.ndarray:  # (G,) float64; 0 for a group without weight
    """Per group, the smallest value at which the cumulative weight reaches half the group's weight.

    Example:
        >>> weighted_median(np.array([0, 0, 0, 1]), np.array([0.3, 1.0, 0.4, 0.9]), np.ones(4), 2).tolist()
        [0.4, 0.9]
    """
    out = np.zeros(num_groups)
    if values.size == 0:
        return out
    order = np.lexsort((values, group))
    group, values, weights = group[order], values[order], weights[order]
    cumulative = np.cumsum(weights)
    total = np.bincount(group, weights=weights, minlength=num_groups)
    first = np.searchsorted(group, np.arange(num_groups))
    before = np.where(first > 0, cumulative[np.maximum(first - 1, 0)], 0.0)
    at = np.searchsorted(cumulative, before + 0.5 * total, side="left")
    inside = (total > 0) & (at < values.size)
    out[inside] = values[np.minimum(at[inside], values.size - 1)]
    return out


def _chunks(rows: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Split consecutive pairs into runs of at most ``limit`` rows (a bigger pair gets a run alone)."""
    ends = np.cumsum(rows)
    spans: list[tuple[int, int]] = []
    lo = 0
    while lo < rows.size:
        before = int(ends[lo - 1]) if lo else 0
        hi = max(int(np.searchsorted(ends, before + limit, side="right")), lo + 1)
        spans.append((lo, hi))
        lo = hi
    return spans
