"""Stage 7: progressive graph clustering of super-primitives into instances (docs/method.md §6).

Input: the super-primitives of stage 5, the primitive kNN graph and the affinity measure of stage 6 (bound to
the mask look-ups and its settings by :func:`panogs_core.stages.affinity.segment_affinity`). Output: a cluster id per
primitive.

Each round takes the current segments (first the super-primitives, then the clusters of the round before),
builds their graph (direct kNN adjacency plus the 2-hop pool, docs/method.md §5.2), recomputes the affinities of
stage 6 on the merged segments, and grows clusters greedily by breadth-first search with that round's
threshold (docs/method.md §6.1); thresholds fall from 0.9 to 0.6. After the last round, clusters of at most 2 parts
and under 200 points join the neighbour they are most alike (docs/method.md §6.2).

Everything between primitives and segments is done once at the super-primitive level: clusters are unions of
super-primitives, so adjacency counts and mask histograms of a round follow by coarsening those of the
super-primitives, never by touching the primitives again.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from scipy import sparse

from panogs_core.errors import ConfigError
from panogs_core.io.npz import save_npz
from panogs_core.progress import ProgressFn, report
from panogs_core.stages.affinity import SegmentAffinity, segment_adjacency

if TYPE_CHECKING:
    from panogs_core.stages.neighbors import KnnGraph
    from panogs_core.stages.superprimitives import SuperPrimitives

UnmergedPolicy = Literal["adjacent", "void", "keep"]


@dataclass(frozen=True, kw_only=True)
class ClusteringConfig:
    """Settings of the progressive clustering (stage 7).

    Attributes:
        thresholds: Affinity threshold of each round, one greedy pass per value, non-increasing (docs/method.md §6:
            ScanNet 0.9, 0.8, 0.7, 0.6; Replica adds 0.5). Unit: affinity (``[1 - ln 2, 1]`` for mode jsd).
        two_hop_weight: Weight of a 2-hop pool member's point count in the BFS score, relative to a direct
            neighbour's (docs/method.md §6.1: 0.5).
        small_cluster_max_parts: A final cluster of at most this many parts (last round's segments) ...
        small_cluster_max_points: ... and fewer than this many primitives is small; it joins the neighbour
            with the highest summed affinity (docs/method.md §6.2: 2 parts, 200 points). ``max_parts = 0``: off.
        unmerged_small: What becomes of a small cluster that has no neighbour with a positive affinity:
            ``"adjacent"`` joins the kNN-adjacent cluster it shares the most kNN edges with (kept when it has
            none), ``"void"`` labels it -1 (the reference's 0), ``"keep"`` leaves it a cluster of its own.
    """

    thresholds: tuple[float, ...] = (0.9, 0.8, 0.7, 0.6)
    two_hop_weight: float = 0.5
    small_cluster_max_parts: int = 2
    small_cluster_max_points: int = 200
    unmerged_small: UnmergedPolicy = "adjacent"

    def __post_init__(self) -> None:
        values = tuple(self.thresholds)
        if not values or not all(isinstance(t, int | float) and math.isfinite(t) for t in values):
            raise ConfigError(f"clustering.thresholds: expected one or more numbers, found {self.thresholds!r}")
        if any(not -1.0 <= t <= 1.0 for t in values):
            raise ConfigError(f"clustering.thresholds: expected values in [-1, 1], found {list(values)}")
        if any(later > earlier for earlier, later in itertools.pairwise(values)):
            raise ConfigError(f"clustering.thresholds: expected non-increasing values, found {list(values)}")
        if not math.isfinite(self.two_hop_weight) or not 0.0 <= self.two_hop_weight <= 1.0:
            raise ConfigError(f"clustering.two_hop_weight: expected a number in [0, 1], found {self.two_hop_weight}")
        for name in ("small_cluster_max_parts", "small_cluster_max_points"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"clustering.{name}: expected an integer >= 0, found {value!r}")
        if self.unmerged_small not in ("adjacent", "void", "keep"):
            raise ConfigError(
                f"clustering.unmerged_small: expected 'adjacent', 'void' or 'keep', found {self.unmerged_small!r}"
            )


@dataclass(frozen=True)
class Clusters:
    """Instance cluster per primitive: dense ids in ``[0, K)``, -1 = void (a removed small cluster)."""

    labels: np.ndarray  # (N,) int64

    @property
    def count(self) -> int:
        """K, the number of clusters (void not counted)."""
        return int(self.labels.max()) + 1 if self.labels.size and self.labels.max() >= 0 else 0

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` at exactly ``path``."""
        save_npz(path, labels=self.labels)

    @classmethod
    def load(cls, path: str | Path) -> Clusters:
        """Read what :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as data:
            return cls(labels=data["labels"].astype(np.int64))


@dataclass(frozen=True)
class _SegmentGraph:
    """One round's graph over the current segments: the pool (direct + 2-hop), both directions, as CSR."""

    sizes: np.ndarray  # (S,) float64, primitives per segment
    indptr: np.ndarray  # (S + 1,) int64
    indices: np.ndarray  # (P,) int64, columns ascending within a row
    direct: np.ndarray  # (P,) bool, adjacent in the kNN graph (else 2-hop only)
    affinity: np.ndarray  # (P,) float64
    knn_edges: np.ndarray  # (P,) float64, primitive kNN edges between the two segments; 0 for 2-hop

    @property
    def num_nodes(self) -> int:
        """S."""
        return int(self.sizes.size)


def progressive_clustering(
    superprimitives: SuperPrimitives,
    knn: KnnGraph,
    affinity: SegmentAffinity,
    cfg: ClusteringConfig,
    *,
    on_progress: ProgressFn | None = None,
) -> Clusters:
    """Group super-primitives into instances by progressive graph clustering (docs/method.md §6).

    Args:
        superprimitives: Stage 5 output; ``labels`` ``(N,)`` int64 dense in ``[0, S)``.
        knn: Primitive kNN graph; ``neighbors`` ``(N, K)`` int64, self excluded.
        affinity: How alike two merged segments are, measured again every round
            (:func:`panogs_core.stages.affinity.segment_affinity` over the same super-primitives).
        cfg: Thresholds, BFS weights and the small-cluster rule.
        on_progress: Called ``(round, rounds)`` after each round.

    Returns:
        Cluster per primitive, dense in ``[0, K)``; -1 only with ``unmerged_small="void"``.

    Raises:
        ShapeError: if ``superprimitives`` and ``knn`` disagree on N.
        InputError: if the affinity cannot be measured (mode ``"language"`` without features).
    """
    sp_labels = np.asarray(superprimitives.labels, dtype=np.int64)
    sp_pairs, sp_edges = segment_adjacency(sp_labels, knn)
    num_sp = int(sp_labels.max()) + 1 if sp_labels.size else 0
    if num_sp == 0:
        return Clusters(labels=np.full(sp_labels.shape, -1, dtype=np.int64))
    sp_sizes = np.bincount(sp_labels[sp_labels >= 0], minlength=num_sp).astype(np.float64)
    segment_of_sp = np.arange(num_sp, dtype=np.int64)
    rounds = len(cfg.thresholds)
    for done, threshold in enumerate(cfg.thresholds, start=1):
        graph = _round_graph(segment_of_sp, sp_pairs, sp_edges, sp_sizes, affinity)
        cluster = _grow_clusters(graph, float(threshold), cfg.two_hop_weight)
        if done == rounds:
            cluster = _merge_small(graph, cluster, cfg)
        segment_of_sp = _dense(cluster[segment_of_sp])
        report(on_progress, done, rounds)
    labels = np.full(sp_labels.shape, -1, dtype=np.int64)
    valid = sp_labels >= 0
    labels[valid] = segment_of_sp[sp_labels[valid]]
    return Clusters(labels=_dense(labels))  # again: an id no primitive carries must not leave a gap


def _round_graph(
    segment_of_sp: np.ndarray,  # (S0,) int64, current segment of each super-primitive
    sp_pairs: np.ndarray,  # (E0, 2) int64, adjacent super-primitives
    sp_edges: np.ndarray,  # (E0,) int64, kNN edges between them
    sp_sizes: np.ndarray,  # (S0,) float64
    affinity_of: SegmentAffinity,
) -> _SegmentGraph:
    num_nodes = int(segment_of_sp.max()) + 1
    direct, edges = _coarsen_pairs(sp_pairs, sp_edges, segment_of_sp, num_nodes)
    pool = _pool_pairs(direct, num_nodes)
    # DEPARTURE (pool only, docs/method.md §6.2, pitfall 16): affinities exist on the pool only, not on the
    # reference's extra pairs of a 200-id block.
    affinity = affinity_of(segment_of_sp, pool).astype(np.float64)
    # Which pool pairs are direct, and their kNN edge count: both key lists are ascending, so one lookup.
    direct_keys = direct[:, 0] * num_nodes + direct[:, 1]
    pool_keys = pool[:, 0] * num_nodes + pool[:, 1]
    at = np.minimum(np.searchsorted(direct_keys, pool_keys), max(direct_keys.size - 1, 0))
    is_direct = direct_keys[at] == pool_keys if direct_keys.size else np.zeros(pool_keys.size, dtype=bool)
    knn_edges = np.where(is_direct, edges[at] if edges.size else 0, 0).astype(np.float64)
    sizes = np.bincount(segment_of_sp, weights=sp_sizes, minlength=num_nodes)
    return _symmetric_graph(sizes, pool, is_direct, affinity, knn_edges)


def _coarsen_pairs(
    pairs: np.ndarray,  # (E0, 2) int64
    edges: np.ndarray,  # (E0,) int64
    segment_of_sp: np.ndarray,  # (S0,) int64
    num_nodes: int,
) -> tuple[np.ndarray, np.ndarray]:  # (E, 2) int64 ascending i < j, (E,) int64
    a = segment_of_sp[pairs[:, 0]]
    b = segment_of_sp[pairs[:, 1]]
    keep = a != b
    lo = np.minimum(a[keep], b[keep])
    hi = np.maximum(a[keep], b[keep])
    keys, inverse = np.unique(lo * num_nodes + hi, return_inverse=True)
    counts = np.bincount(inverse.reshape(-1), weights=edges[keep], minlength=keys.size).astype(np.int64)
    return np.stack([keys // num_nodes, keys % num_nodes], axis=1), counts


def _pool_pairs(direct: np.ndarray, num_nodes: int) -> np.ndarray:  # (P, 2) int64, ascending, i < j
    """Direct neighbours and 2-hop neighbours (``A @ A``), diagonal cleared (docs/method.md §5.2)."""
    ones = np.ones(direct.shape[0], dtype=np.int64)
    adjacency = sparse.csr_matrix((ones, (direct[:, 0], direct[:, 1])), shape=(num_nodes, num_nodes))
    adjacency = adjacency + adjacency.T
    pool = sparse.triu(adjacency @ adjacency + adjacency, k=1).tocoo()
    keys = np.unique(pool.row.astype(np.int64) * num_nodes + pool.col.astype(np.int64))
    return np.stack([keys // num_nodes, keys % num_nodes], axis=1)


def _symmetric_graph(
    sizes: np.ndarray,  # (S,) float64
    pool: np.ndarray,  # (P, 2) int64, i < j
    is_direct: np.ndarray,  # (P,) bool
    affinity: np.ndarray,  # (P,) float64
    knn_edges: np.ndarray,  # (P,) float64
) -> _SegmentGraph:
    rows = np.concatenate([pool[:, 0], pool[:, 1]])
    cols = np.concatenate([pool[:, 1], pool[:, 0]])
    order = np.lexsort((cols, rows))  # row-major, columns ascending: BFS visits neighbours in ascending id
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=sizes.size))]).astype(np.int64)
    return _SegmentGraph(
        sizes=sizes,
        indptr=indptr,
        indices=cols[order],
        direct=np.concatenate([is_direct, is_direct])[order],
        affinity=np.concatenate([affinity, affinity])[order],
        knn_edges=np.concatenate([knn_edges, knn_edges])[order],
    )


def _grow_clusters(graph: _SegmentGraph, threshold: float, two_hop_weight: float) -> np.ndarray:  # (S,) int64
    """One greedy BFS region-growing pass, exactly as docs/method.md §6.1.

    Seeds are taken in ascending id; a neighbour j of a member joins when the affinity of j to the cluster's
    members, weighted by their point counts (2-hop pool members at ``two_hop_weight``), is at least
    ``threshold``. A rejected j stays free: another member may test it again, or it seeds its own cluster.
    """
    count_weight = graph.sizes[graph.indices] * np.where(graph.direct, 1.0, two_hop_weight)
    affinity_weight = graph.affinity * count_weight
    indptr = graph.indptr.tolist()
    direct_lists = _direct_neighbour_lists(graph)
    cluster = np.full(graph.num_nodes, -1, dtype=np.int64)
    current = 0
    for seed in range(graph.num_nodes):
        if cluster[seed] >= 0:
            continue
        cluster[seed] = current
        queue = deque([seed])
        while queue:
            for j in direct_lists[queue.popleft()]:
                if cluster[j] >= 0:
                    continue
                lo, hi = indptr[j], indptr[j + 1]
                inside = cluster[graph.indices[lo:hi]] == current  # never empty: the member that reached j
                total = count_weight[lo:hi] @ inside
                if total > 0 and (affinity_weight[lo:hi] @ inside) / total >= threshold:
                    cluster[j] = current
                    queue.append(j)
        current += 1
    return cluster


def _direct_neighbour_lists(graph: _SegmentGraph) -> list[list[int]]:
    """Per node, its direct neighbours in ascending id, as Python lists (the BFS walks them one by one)."""
    rows = np.repeat(np.arange(graph.num_nodes), np.diff(graph.indptr))[graph.direct]
    cols = graph.indices[graph.direct].tolist()
    bounds = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=graph.num_nodes))]).tolist()
    return [cols[bounds[i] : bounds[i + 1]] for i in range(graph.num_nodes)]


def _merge_small(
    graph: _SegmentGraph,
    cluster: np.ndarray,  # (S,) int64, dense cluster per node
    cfg: ClusteringConfig,
) -> np.ndarray:  # (S,) int64, -1 = void
    """Small clusters join their most alike neighbour (docs/method.md §6.2); unmergeable ones follow the policy."""
    num_clusters = int(cluster.max()) + 1
    parts = np.bincount(cluster, minlength=num_clusters)
    points = np.bincount(cluster, weights=graph.sizes, minlength=num_clusters)
    small = np.flatnonzero((parts <= cfg.small_cluster_max_parts) & (points < cfg.small_cluster_max_points))
    if small.size == 0:
        return cluster
    order = np.argsort(cluster, kind="stable")
    starts = np.concatenate([[0], np.cumsum(parts)])
    groups = [order[starts[c] : starts[c + 1]] for c in small]  # ascending cluster id, as the reference
    label = cluster.copy()
    pending = np.isin(cluster, small)  # the reference's "unmerged" primitives
    _absorb(graph, groups, label, pending, graph.affinity)
    if cfg.unmerged_small == "adjacent":
        # DEPARTURE (docs/method.md §6.2): an unmerged small cluster joins the cluster it shares the most kNN
        # edges with, where the reference labels it 0 ("void": -1, "keep": left alone).
        _absorb(graph, groups, label, pending, graph.knn_edges)
    elif cfg.unmerged_small == "void":
        label[pending] = -1
    return label


def _absorb(
    graph: _SegmentGraph,
    groups: list[np.ndarray],  # node ids of each small cluster, ascending cluster id
    label: np.ndarray,  # (S,) int64, updated in place
    pending: np.ndarray,  # (S,) bool, updated in place: nodes of small clusters not merged yet
    weight: np.ndarray,  # (P,) float64, per pool entry: how strongly the two nodes belong together
) -> None:
    """Sweep the small clusters until none changes: each joins the node with the highest summed weight.

    Targets still pending are skipped, and a cluster with no positive weight to any settled node waits for the
    next sweep (docs/method.md §6.2). It takes the target's current label, so chains of merges resolve.
    """
    changed = True
    while changed:
        changed = False
        for nodes in groups:
            if not pending[nodes[0]]:
                continue
            entries = np.concatenate([np.arange(graph.indptr[n], graph.indptr[n + 1]) for n in nodes])
            targets = graph.indices[entries]
            settled = ~pending[targets]
            if not settled.any():
                continue
            ids, inverse = np.unique(targets[settled], return_inverse=True)
            score = np.bincount(inverse.reshape(-1), weights=weight[entries][settled])
            best = int(np.argmax(score))  # ties: lowest node id (the reference's argsort is unstable)
            if score[best] <= 0:
                continue
            label[nodes] = label[ids[best]]
            pending[nodes] = False
            changed = True


def _dense(labels: np.ndarray) -> np.ndarray:  # (M,) int64 dense in [0, K), -1 kept
    """Renumber ids to ``0..K-1`` in ascending order of the old id (docs/method.md §5.2); -1 stays -1."""
    out = np.full(labels.shape, -1, dtype=np.int64)
    valid = labels >= 0
    out[valid] = np.unique(labels[valid], return_inverse=True)[1].reshape(-1)
    return out
