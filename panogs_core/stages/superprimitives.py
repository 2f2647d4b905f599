"""Stage 5: super-primitives by language-guided graph cuts (docs/method.md §4).

The primitives' kNN graph is cut with the Felzenszwalb-Huttenlocher (FH) algorithm. Edge weights come from the
normals (``1 - n_a . n_b``, squared across convex edges) and are multiplied by a penalty where the two points'
language features disagree; a merge additionally requires the two segments' root points to agree in language.
Segments smaller than ``min_size`` are then merged into a neighbour.

Inputs: points ``(N, 3)``, unoriented normals ``(N, 3)``, decoded language features ``(N, D)`` (or ``None``
for the geometry-only ablation), the kNN graph (:mod:`panogs_core.stages.neighbors`) and, optionally, the mask look-ups
(:mod:`panogs_core.stages.masks`). Output: :class:`SuperPrimitives`, a dense segment id per
point.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.io.npz import save_npz
from panogs_core.progress import ProgressFn, report
from panogs_core.stages.masks import MaskObservations
from panogs_core.stages.neighbors import KnnGraph

_EDGE_CHUNK = 1 << 17  # edges per tight-loop chunk between progress reports (and cancellation points)
_DOT_CHUNK = 2048  # pairs per chunk of _pair_dots (the small-segment merge's (2048, D) gathers of mean features)
# Points per chunk of neighbour dots: the (64, K=7, D=512) float32 gather is 0.9 MiB and stays in a core's L2
# between its write and the einsum's read (at 2048 points it was 28 MiB: 0.19 s against 0.11 s on 78,556 points).
_NEIGHBOR_DOT_CHUNK = 64


@dataclass(frozen=True, kw_only=True)
class SuperPrimitiveConfig:
    """Settings of the graph cut (docs/method.md §4; defaults: the reference's ScanNet settings)."""

    k_neighbors: int = 7  # graph neighbours per point, self excluded (reference k_neigbor 8 includes self)
    k_thresh: float = 0.1  # FH constant: tau = k_thresh / |segment| (docs/method.md §4.5; Replica 0.15)
    language_penalty: float = 20.0  # edge weight factor where point features disagree (docs/method.md §4.4)
    edge_cosine: float = 0.9  # features disagree when 1 - f_a . f_b > 1 - edge_cosine (reference: s > 0.1)
    merge_cosine: float = 0.9  # a merge needs cos(root features) strictly above this (docs/method.md §4.5)
    min_size: int = 20  # points; smaller segments are merged into a neighbour (reference seg_min_verts)
    use_language: bool = True  # False: geometry-only graph cut (the "without language" ablation)
    # DEPARTURE candidate, off (docs/method.md §4.4): True uses 1 - |n_a . n_b|, blind to the unoriented normals' signs.
    orient_invariant: bool = False
    # DEPARTURE (docs/method.md §4.6): "language" joins a segment under min_size to the adjacent one of closest mean
    # language feature; "construction" (the reference) to the first in edge order, "weight" by ascending edge weight.
    small_merge_order: Literal["construction", "weight", "language"] = "language"
    # DEPARTURE (mask split, docs/method.md §4.7): a segment whose largest 2D mask holds under split_purity of its
    # members seen inside masks is cut in two along the frame that shows the split best; 0 turns it off.
    split_purity: float = 0.75

    def __post_init__(self) -> None:
        _require(self.k_neighbors >= 1, "k_neighbors", ">= 1", self.k_neighbors)
        _require(math.isfinite(self.k_thresh) and self.k_thresh > 0, "k_thresh", "> 0", self.k_thresh)
        _require(
            math.isfinite(self.language_penalty) and self.language_penalty >= 1.0,
            "language_penalty",
            ">= 1",
            self.language_penalty,
        )
        _require(-1.0 <= self.edge_cosine <= 1.0, "edge_cosine", "a cosine in [-1, 1]", self.edge_cosine)
        _require(-1.0 <= self.merge_cosine <= 1.0, "merge_cosine", "a cosine in [-1, 1]", self.merge_cosine)
        _require(self.min_size >= 1, "min_size", ">= 1", self.min_size)
        _require(0.0 <= self.split_purity <= 1.0, "split_purity", "a fraction in [0, 1]", self.split_purity)
        _require(
            self.small_merge_order in ("construction", "weight", "language"),
            "small_merge_order",
            "'construction', 'weight' or 'language'",
            self.small_merge_order,
        )


def _require(ok: bool, name: str, expected: str, value: object) -> None:
    if not ok:
        raise ConfigError(f"superprimitives.{name}: expected {expected}, found {value!r}")


@dataclass(frozen=True)
class SuperPrimitives:
    """Graph-cut segments of the primitives."""

    labels: np.ndarray  # (N,) int64, dense in [0, S)

    @property
    def count(self) -> int:
        """Number of super-primitives S."""
        return int(self.labels.max()) + 1 if self.labels.size else 0

    def save(self, path: str | Path) -> None:
        """Write ``labels`` to one ``.npz`` at exactly ``path``."""
        save_npz(path, labels=self.labels)

    @classmethod
    def load(cls, path: str | Path) -> SuperPrimitives:
        """Read what :meth:`save` wrote (no pickles)."""
        with np.load(Path(path), allow_pickle=False) as data:
            return cls(labels=data["labels"].astype(np.int64))


def graph_cut_superprimitives(
    points: np.ndarray,  # (N, 3) float, world metres
    normals: np.ndarray,  # (N, 3) float, unit, unoriented
    features: np.ndarray | None,  # (N, D) float32 unit rows, or None
    knn: KnnGraph,
    cfg: SuperPrimitiveConfig,
    *,
    masks: MaskObservations | None = None,
    on_progress: ProgressFn | None = None,
) -> SuperPrimitives:
    """Partition the primitives into super-primitives by language-guided FH graph cuts (docs/method.md §4.4-4.7).

    Args:
        points: Primitive centres. ``(N, 3)`` float, world frame, metres.
        normals: Unit normals, sign arbitrary. ``(N, 3)`` float.
        features: Decoded language features, ``(N, D)`` unit rows; ``None`` (or ``cfg.use_language`` False)
            runs the geometry-only ablation: no edge penalty and no merge check.
        knn: Neighbour graph of ``points``; its first ``cfg.k_neighbors`` columns are used.
        cfg: Neighbour count, FH constant, language thresholds and minimum segment size.
        masks: The 2D mask ids under the primitives (:mod:`panogs_core.stages.masks`); segments the masks keep
            dividing are cut in two (``cfg.split_purity``). None: normals and language only, as the reference.
        on_progress: Called as ``on_progress(done, total)`` between chunks of edges; may raise ``Cancelled``.

    Returns:
        Dense segment id per point, ordered by the segments' root point index (the reference's ``init_seg``).

    Raises:
        ShapeError: if the arrays disagree on ``N`` or have the wrong shape.
        InputError: if the graph has fewer than ``cfg.k_neighbors`` columns or an input is not finite.

    Example:
        Two perpendicular planes (a floor and a wall) give two super-primitives:

        >>> u, v = (g.ravel() for g in np.meshgrid(np.arange(20) * 0.05, np.arange(20) * 0.05))
        >>> floor = np.c_[u + 0.05, v, np.zeros(400)]
        >>> wall = np.c_[np.zeros(400), v, u + 0.05]
        >>> points = np.concatenate([floor, wall])
        >>> normals = np.repeat([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], 400, axis=0)
        >>> from panogs_core.stages.neighbors import build_knn
        >>> knn = build_knn(points, 7)
        >>> graph_cut_superprimitives(points, normals, None, knn, SuperPrimitiveConfig()).count
        2
    """
    points, normals, features, neighbors = _check_inputs(points, normals, features, knn, cfg)
    n = points.shape[0]
    src, dst, weights = edge_weights(points, normals, features, neighbors, cfg)
    total = -(-src.size // _EDGE_CHUNK) + 2
    report(on_progress, 1, total)

    def chunk_done(done_chunks: int) -> None:
        report(on_progress, 1 + done_chunks, total)

    order = np.argsort(weights, kind="stable")  # ties keep construction order (docs/method.md pitfall 12)
    forest = _Forest(n)
    _fh_merge(forest, src[order], dst[order], weights[order], features, cfg, chunk_done)
    if cfg.small_merge_order == "language" and features is not None:
        roots = _merge_small_language(forest.roots(), src, dst, features, cfg.min_size)
    else:
        by_weight = cfg.small_merge_order != "construction"
        _merge_small(forest, src[order] if by_weight else src, dst[order] if by_weight else dst, cfg.min_size)
        roots = forest.roots()
    _, labels = np.unique(roots, return_inverse=True)
    labels = labels.astype(np.int64)
    if masks is not None and cfg.split_purity > 0:
        labels = split_straddling(labels, points, masks, cfg.split_purity, cfg.min_size)
    report(on_progress, total, total)
    return SuperPrimitives(labels=labels)


def split_straddling(
    labels: np.ndarray,  # (N,) int64 dense segment ids
    points: np.ndarray,  # (N, 3) float
    masks: MaskObservations,
    min_purity: float,
    min_size: int,
    rounds: int = 2,
) -> np.ndarray:  # (N,) int64 dense segment ids
    """Cut segments that the 2D masks keep dividing (``SuperPrimitiveConfig.split_purity``).

    Purity of a segment: over the mask frames, the members seen in the frame's largest mask of that segment,
    divided by all its members seen in masks. A segment below ``min_purity`` is cut along the frame whose
    second-largest mask holds the most members: each mask there with at least ``min_size / 2`` members seeds a
    part, every other member joins the part of its nearest seed, and parts under ``min_size`` rejoin the part
    nearest to them. Repeated up to ``rounds`` times (a frame may not show every object of a segment).
    """
    labels = np.asarray(labels, dtype=np.int64)
    if masks.point_index.size == 0 or labels.size == 0:
        return labels
    frame_of = np.repeat(np.arange(masks.num_frames, dtype=np.int64), np.diff(masks.offsets))
    index = masks.point_index.astype(np.int64)
    span = int(masks.label.max()) + 1
    for _ in range(rounds):
        num = int(labels.max()) + 1
        keys, counts = np.unique((labels[index] * masks.num_frames + frame_of) * span + masks.label, return_counts=True)
        group = keys // span  # segment * V + frame, ascending
        starts = np.flatnonzero(np.diff(group, prepend=-1))
        largest = np.maximum.reduceat(counts, starts)
        total = np.add.reduceat(counts, starts)
        segment = group[starts] // max(masks.num_frames, 1)
        seen = np.bincount(segment, weights=total, minlength=num)
        purity = np.bincount(segment, weights=largest, minlength=num) / np.maximum(seen, 1)
        straddling = np.flatnonzero((purity < min_purity) & (seen >= min_size))
        # Members and observations of every segment as slices of one stable sort (ascending within a segment),
        # instead of an O(N) scan per straddling segment.
        member_of, member_start = _grouped(labels, num)
        obs_of, obs_start = _grouped(labels[index], num)
        changed = False
        for seg in straddling.tolist():
            members = member_of[member_start[seg] : member_start[seg + 1]]
            obs = obs_of[obs_start[seg] : obs_start[seg + 1]]
            parts = _cut(members, obs, points, masks, frame_of, index, min_size)
            if parts is not None:
                labels[members[parts > 0]] = num + parts[parts > 0] - 1
                num += int(parts.max())
                changed = True
        if not changed:
            break
    return np.unique(labels, return_inverse=True)[1].reshape(-1).astype(np.int64)


def _grouped(keys: np.ndarray, num: int) -> tuple[np.ndarray, np.ndarray]:  # (K,) positions, (num + 1,) starts
    """Positions of ``keys`` (ints in ``[0, num)``) sorted by key, stable, and where each key's run starts."""
    order = np.argsort(keys, kind="stable")
    return order, np.searchsorted(keys[order], np.arange(num + 1))


def _cut(
    members: np.ndarray,  # (M,) int64 point indices of one segment, ascending
    obs: np.ndarray,  # (O,) int64 positions of its mask observations, ascending
    points: np.ndarray,  # (N, 3)
    masks: MaskObservations,
    frame_of: np.ndarray,  # (T,) frame of each observation
    index: np.ndarray,  # (T,) int64 primitive of each observation
    min_size: int,
) -> np.ndarray | None:  # (M,) part of each member, 0..K-1 with K >= 2; None when no cut is worth making
    """The cut of :func:`split_straddling` for one segment."""
    frames, ids = frame_of[obs], masks.label[obs].astype(np.int64)
    span = int(ids.max()) + 1
    keys, counts = np.unique(frames * span + ids, return_counts=True)
    key_frame = keys // span
    best_frame, best_second = -1, 0
    for f in np.unique(key_frame).tolist():
        in_frame = np.sort(counts[key_frame == f])
        if in_frame.size >= 2 and in_frame[-2] > best_second:
            best_frame, best_second = f, int(in_frame[-2])
    if best_frame < 0 or best_second < min_size / 2:
        return None
    seeds_of_frame = keys[(key_frame == best_frame) & (counts >= min_size / 2)] % span  # mask ids seeding parts
    in_frame = obs[frames == best_frame]
    seed_obs = in_frame[np.isin(masks.label[in_frame], seeds_of_frame)]
    seed_points = index[seed_obs]
    seed_part = np.searchsorted(np.sort(seeds_of_frame), masks.label[seed_obs])  # (S,) 0..K-1
    _, nearest = cKDTree(points[seed_points]).query(points[members], k=1)
    part = seed_part[nearest]  # (M,)
    sizes = np.bincount(part, minlength=seeds_of_frame.size)
    if np.count_nonzero(sizes >= min_size) < 2:
        return None
    small = sizes[part] < min_size  # members of parts too small to stand alone rejoin the nearest big part
    if small.any():
        big = ~small
        _, nearest_big = cKDTree(points[members[big]]).query(points[members[small]], k=1)
        part[small] = part[big][nearest_big]
    return np.unique(part, return_inverse=True)[1].reshape(-1)


def _check_inputs(
    points: np.ndarray,
    normals: np.ndarray,
    features: np.ndarray | None,
    knn: KnnGraph,
    cfg: SuperPrimitiveConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Validate and convert once; features come back unit-normalised float32 (None when language is off)."""
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points: expected shape (N, 3), found {points.shape}")
    n = points.shape[0]
    if normals.shape != (n, 3):
        raise ShapeError(f"normals: expected shape ({n}, 3), found {normals.shape}")
    neighbors = np.asarray(knn.neighbors)
    if neighbors.ndim != 2 or neighbors.shape[0] != n:
        raise ShapeError(f"knn.neighbors: expected shape ({n}, K), found {neighbors.shape}")
    if neighbors.size and (neighbors.min() < 0 or neighbors.max() >= n):
        raise InputError(f"knn.neighbors: expected indices in [0, {n}), found [{neighbors.min()}, {neighbors.max()}]")
    if neighbors.shape[1] < cfg.k_neighbors:
        raise InputError(f"knn: has {neighbors.shape[1]} neighbours per point, cfg.k_neighbors is {cfg.k_neighbors}")
    if not (np.isfinite(points).all() and np.isfinite(normals).all()):
        raise InputError("points / normals: contain NaN or infinite values")
    if features is None or not cfg.use_language:
        return points, normals, None, neighbors[:, : cfg.k_neighbors]
    features = np.asarray(features, dtype=np.float32)
    if features.ndim != 2 or features.shape[0] != n:
        raise ShapeError(f"features: expected shape ({n}, D), found {features.shape}")
    # Squared norms without an (N, D) temporary; a NaN or infinity in a row makes its norm non-finite.
    norms = np.sqrt(np.einsum("nd,nd->n", features, features))
    if not np.isfinite(norms).all():
        raise InputError("features: contains NaN or infinite values")
    if not np.allclose(norms, 1.0, atol=1e-5):  # the field's and the fusion's rows are unit already: no copy
        features = features / np.maximum(norms, 1e-12).astype(np.float32)[:, None]
    return points, normals, features, neighbors[:, : cfg.k_neighbors]


def edge_weights(
    points: np.ndarray,  # (N, 3) float64
    normals: np.ndarray,  # (N, 3) float64, unit
    features: np.ndarray | None,  # (N, D) float32 unit rows, or None
    neighbors: np.ndarray,  # (N, K) int64
    cfg: SuperPrimitiveConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directed kNN edges in construction order (point i, then its neighbours by distance) and their weights.

    docs/method.md §4.4: ``w = 1 - n_a . n_b``; squared when ``n_b . (X_b - X_a) > 0`` (convex; a duplicate point
    gives 0 there, so no squaring, like the reference's NaN); times ``language_penalty`` when
    ``1 - f_a . f_b`` exceeds ``1 - edge_cosine``.

    Returns:
        ``src`` ``(E,)`` int64, ``dst`` ``(E,)`` int64 and ``weights`` ``(E,)`` float64, ``E = N * K``.
    """
    n, k = neighbors.shape
    src = np.repeat(np.arange(n, dtype=np.int64), k)  # (E,)
    dst = neighbors.reshape(-1).astype(np.int64)  # (E,)
    normal_dst = normals[dst]  # (E, 3)
    cos_normals = np.einsum("ij,ij->i", normals[src], normal_dst)
    if cfg.orient_invariant:
        cos_normals = np.abs(cos_normals)
    weights = 1.0 - cos_normals
    convex = np.einsum("ij,ij->i", normal_dst, points[dst] - points[src]) > 0.0
    weights = np.where(convex, weights * weights, weights)
    if features is not None:
        dissimilar = 1.0 - _neighbor_dots(features, neighbors).reshape(-1) > np.float32(1.0 - cfg.edge_cosine)
        weights = np.where(dissimilar, weights * cfg.language_penalty, weights)
    return src, dst, weights


def _pair_dots(rows: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:  # (P,) rows.dtype
    """``rows[a[p]] . rows[b[p]]`` in chunks of pairs, never two (P, D) gathers (on a 47k-point scan room they
    were 184 MB, the stage's peak)."""
    dots = np.empty(a.size, dtype=rows.dtype)
    for start in range(0, a.size, _DOT_CHUNK):
        pairs = slice(start, start + _DOT_CHUNK)
        dots[pairs] = np.einsum("ij,ij->i", rows[a[pairs]], rows[b[pairs]])
    return dots


def _neighbor_dots(features: np.ndarray, neighbors: np.ndarray) -> np.ndarray:  # (N, K) float32
    """``f_i . f_neighbors[i, j]`` in chunks of points, never an (E, D) array.

    The chunk size does not change a bit: einsum reduces each (point, neighbour) pair's D products on its own,
    with the same kernel for every chunk (the operands' strides do not depend on it).
    """
    dots = np.zeros(neighbors.shape, dtype=np.float32)
    for start in range(0, neighbors.shape[0], _NEIGHBOR_DOT_CHUNK):
        rows = slice(start, start + _NEIGHBOR_DOT_CHUNK)
        dots[rows] = np.einsum("nd,nkd->nk", features[rows], features[neighbors[rows]])
    return dots


class _Forest:
    """Union-find state as flat Python lists (fastest for the sequential loops): parent, rank, size."""

    def __init__(self, n: int) -> None:
        self.parent = list(range(n))
        self.rank = [0] * n
        self.size = [1] * n

    def roots(self) -> np.ndarray:  # (N,) int64
        """Root of every element, by vectorised pointer jumping (also fully compresses ``parent``)."""
        parent = np.asarray(self.parent, dtype=np.int64)
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
        self.parent = parent.tolist()
        return parent


def _fh_merge(
    forest: _Forest,
    src: np.ndarray,  # (E,) int64, sorted by weight
    dst: np.ndarray,  # (E,) int64
    weights: np.ndarray,  # (E,) float64, ascending
    features: np.ndarray | None,  # (N, D) float32 unit rows, or None
    cfg: SuperPrimitiveConfig,
    chunk_done: Callable[[int], None],
) -> None:
    """FH merge with the root-point language check (docs/method.md §4.5), in place on ``forest``.

    A merge of segments A and B (roots) needs ``w <= tau[A]``, ``w <= tau[B]`` and, with language,
    ``f[A] . f[B] > merge_cosine`` on the root points' own features; the new root R gets
    ``tau[R] = w + k_thresh / |R|``. Union by rank decides the root: the higher rank wins, ties go to B.
    """
    parent, rank, size = forest.parent, forest.rank, forest.size
    k_thresh, merge_cos = cfg.k_thresh, cfg.merge_cosine
    tau = [k_thresh] * len(parent)
    # No root's tau can exceed the largest tau ever set; edges come in ascending weight, so the first edge
    # above it ends the pass (exactly: nothing after it could merge).
    tau_max = k_thresh
    for chunk, start in enumerate(range(0, src.size, _EDGE_CHUNK)):
        stop = start + _EDGE_CHUNK
        for a, b, w in zip(src[start:stop].tolist(), dst[start:stop].tolist(), weights[start:stop].tolist()):
            if w > tau_max:
                chunk_done(-(-src.size // _EDGE_CHUNK))
                return
            # Most points' parent is their root already (compressed paths): one look-up each, no loop.
            root_a = parent[a]
            if parent[root_a] != root_a:
                while parent[root_a] != root_a:
                    root_a = parent[root_a]
                while parent[a] != root_a:  # path compression
                    parent[a], a = root_a, parent[a]
            root_b = parent[b]
            if parent[root_b] != root_b:
                while parent[root_b] != root_b:
                    root_b = parent[root_b]
                while parent[b] != root_b:
                    parent[b], b = root_b, parent[b]
            if root_a == root_b or w > tau[root_a] or w > tau[root_b]:
                continue
            # ndarray.dot and @ both end in numpy's float32 dot (cblas_sdot) for two 1-D rows: the same bits,
            # without the matmul ufunc's dispatch (1.2 against 1.7 us a call, ~87k calls on 78,556 points).
            if features is not None and float(features[root_a].dot(features[root_b])) <= merge_cos:
                continue
            if rank[root_a] > rank[root_b]:
                root_a, root_b = root_b, root_a  # attach the lower-rank root under the other
            elif rank[root_a] == rank[root_b]:
                rank[root_b] += 1
            parent[root_a] = root_b
            size[root_b] += size[root_a]
            tau[root_b] = w + k_thresh / size[root_b]
            if tau[root_b] > tau_max:
                tau_max = tau[root_b]
        chunk_done(chunk + 1)


def _merge_small_language(
    roots: np.ndarray,  # (N,) int64, FH root of every point
    src: np.ndarray,  # (E,) int64
    dst: np.ndarray,  # (E,) int64
    features: np.ndarray,  # (N, D) float32 unit rows
    min_size: int,
) -> np.ndarray:  # (N,) int64, representative point (smallest root of the merged pieces) of every point
    """Small segments join the adjacent segment whose mean language feature is closest, in rounds.

    Each round, every segment below ``min_size`` picks, among the segments it shares a kNN edge with, the one
    of highest cosine between mean features (ties: the lowest id); all picks are applied at once (connected
    components), means are updated from the summed features, and rounds repeat until no small segment has a
    neighbour left to join.
    """
    seg_root, seg = np.unique(roots, return_inverse=True)  # seg (N,) dense ids; seg_root: smallest point id
    seg = seg.astype(np.int64)
    sums = np.asarray(
        sparse.csr_matrix((np.ones(seg.size, np.float32), (seg, np.arange(seg.size))), shape=(seg_root.size, seg.size))
        @ features,
        dtype=np.float64,
    )  # (S, D)
    sizes = np.bincount(seg, minlength=seg_root.size)
    rep = seg_root.astype(np.int64)  # (S,) representative point of each segment
    while True:
        a, b = seg[src], seg[dst]
        cand = (a != b) & (sizes[a] < min_size)
        if not cand.any():
            break
        pa, pb = np.unique(np.stack([a[cand], b[cand]], axis=1), axis=0).T
        unit = sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12)
        score = _pair_dots(unit, pa, pb)
        order = np.lexsort((pb, -score, pa))  # per small segment: best score first, then lowest id
        first = order[np.r_[True, pa[order][1:] != pa[order][:-1]]]
        num = sizes.size
        graph = sparse.csr_matrix((np.ones(first.size), (pa[first], pb[first])), shape=(num, num))
        _, comp = csgraph.connected_components(graph, directed=True, connection="weak")
        count = int(comp.max()) + 1
        merged = np.full(count, np.iinfo(np.int64).max, np.int64)
        np.minimum.at(merged, comp, rep)
        rep = merged
        sums = np.asarray(sparse.csr_matrix((np.ones(num), (comp, np.arange(num))), shape=(count, num)) @ sums)
        sizes = np.bincount(comp, weights=sizes, minlength=count).astype(np.int64)
        seg = comp[seg].astype(np.int64)
    return rep[seg]


def _merge_small(forest: _Forest, src: np.ndarray, dst: np.ndarray, min_size: int) -> None:
    """Merge segments below ``min_size`` along the edges in construction order (docs/method.md §4.6), in place.

    Only edges that can merge are visited: segments only grow, so an edge whose two segments are already both
    at least ``min_size`` (or already the same) at the start never qualifies later.
    """
    roots = forest.roots()  # (N,)
    small = np.bincount(roots, minlength=roots.size)[roots] < min_size  # (N,) per point: its segment is small
    candidate = (roots[src] != roots[dst]) & (small[src] | small[dst])
    parent, rank, size = forest.parent, forest.rank, forest.size
    for a, b in zip(src[candidate].tolist(), dst[candidate].tolist()):
        root_a = a
        while parent[root_a] != root_a:
            root_a = parent[root_a]
        root_b = b
        while parent[root_b] != root_b:
            root_b = parent[root_b]
        if root_a == root_b or (size[root_a] >= min_size and size[root_b] >= min_size):
            continue
        if rank[root_a] > rank[root_b]:
            root_a, root_b = root_b, root_a
        elif rank[root_a] == rank[root_b]:
            rank[root_b] += 1
        parent[root_a] = root_b
        size[root_b] += size[root_a]
