"""The merge of a tiled run: the tiles' labels as those of one scene (docs/method.md §16.2).

* Each primitive takes its class and instance from the tile whose core holds it.
* A thing instance cut by a seam is one instance: instance a of tile t and instance b of tile u are joined when
  they share a class and each is the other's best overlap where the two tiles both label primitives (t's halo
  over u's core, u's halo over t's core), with at least ``min_overlap`` shared primitives. Joins are transitive
  (an instance at a corner of four tiles is one).
* Stuff is one segment per class across the building.
* Ids as an untiled run numbers them: things by their first primitive (scene order), then stuff by class; an
  instance's feature and score are its tiles' pieces' averaged by their core primitives, its centroid, box and
  count those of its primitives.

Memory: O(N) labels and the halo's (point, instance) pairs; one tile's files at a time, never a feature array
N x D.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panogs_core.io.run_folder import LABELS_NPZ, load_result
from panogs_core.stages.labeling import InstanceInfo, PanopticLabels
from panogs_core.types import Vocabulary


@dataclass(frozen=True)
class TileLabels:
    """What the merge reads of one tile: its primitives' global ids, which are its core, and its labels."""

    point_index: np.ndarray  # (n,) int64 ascending, the scene's primitive ids
    core: np.ndarray  # (n,) bool
    semantic: np.ndarray  # (n,) int64
    instance: np.ndarray  # (n,) int64, ids of ``instances``
    superprimitive: np.ndarray  # (n,) int64
    cluster: np.ndarray  # (n,) int64
    instances: tuple[InstanceInfo, ...]

    @classmethod
    def from_run(cls, run_dir: Path, point_index: np.ndarray, core: np.ndarray) -> TileLabels:
        """A tile's finished run folder (``labels.npz``, ``instances.json``, ``instance_features.npy``)."""
        with np.load(LABELS_NPZ.path(run_dir), allow_pickle=False) as npz:
            arrays = {k: npz[k].astype(np.int64) for k in ("semantic", "instance", "superprimitive", "cluster")}
        return cls(point_index=point_index, core=core, instances=load_result(run_dir).instances, **arrays)


@dataclass(frozen=True)
class MergedLabels:
    """The scene's labels, as an untiled run's stage 8 gives them, plus the merge's own counts."""

    labels: PanopticLabels
    superprimitive: np.ndarray  # (N,) int64, tile-offset ids, -1 void
    cluster: np.ndarray  # (N,) int64, tile-offset ids, -1 void
    seam_joins: int  # pairs of pieces joined across a seam


class _UnionFind:
    def __init__(self, size: int) -> None:
        self.parent = np.arange(size)

    def find(self, a: int) -> int:
        root = a
        while self.parent[root] != root:
            root = int(self.parent[root])
        while self.parent[a] != root:
            self.parent[a], a = root, int(self.parent[a])
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def merge_tiles(
    tiles: Iterable[TileLabels],
    points: np.ndarray,  # (N, 3) float32, the scene's primitives
    vocabulary: Vocabulary,
    *,
    min_overlap: int = 10,
) -> MergedLabels:
    """Merge the tiles' labels into the scene's.

    Args:
        tiles: The tiles in plan order (any iterable: a generator reads one tile's files at a time).
        points: The scene's primitive centres.
        vocabulary: The run's label set (thing or stuff per class).
        min_overlap: Fewest shared halo primitives for a seam join (ours: 10, a few centimetres of surface at the
            synthetic scenes' spacing; a real overlap across a 1 m halo is hundreds).
    """
    n = points.shape[0]
    is_thing = vocabulary.is_thing
    semantic = np.full(n, -1, np.int64)
    piece = np.full(n, -1, np.int64)  # the owning tile's piece (tile offset + its instance id) at each primitive
    superprimitive = np.full(n, -1, np.int64)
    cluster = np.full(n, -1, np.int64)
    infos: list[InstanceInfo] = []  # every tile's instances, piece id = position here
    halo_points, halo_pieces = [], []  # primitives of a tile's halo and that tile's piece there
    offsets = {"sp": 0, "cluster": 0}
    for tile in tiles:
        base = len(infos)
        infos.extend(tile.instances)
        own = tile.point_index[tile.core]
        semantic[own] = tile.semantic[tile.core]
        local = tile.instance[tile.core]
        piece[own] = np.where(local >= 0, local + base, -1)
        for name, dest, src in (("sp", superprimitive, tile.superprimitive), ("cluster", cluster, tile.cluster)):
            part = src[tile.core]
            dest[own] = np.where(part >= 0, part + offsets[name], -1)
            offsets[name] += int(src.max()) + 1 if src.size else 0
        halo = ~tile.core & (tile.instance >= 0)
        halo_points.append(tile.point_index[halo])
        halo_pieces.append(tile.instance[halo] + base)
    piece_class = np.array([i.class_index for i in infos], np.int64)
    piece_thing = is_thing[piece_class] if infos else np.zeros(0, bool)
    groups = _UnionFind(len(infos))
    joins = _join_across_seams(groups, np.concatenate(halo_points), np.concatenate(halo_pieces), piece,
                               piece_class, piece_thing, min_overlap)  # fmt: skip
    instance, rows = _number_instances(groups, piece, piece_class, piece_thing, semantic, is_thing)
    instances = _instance_infos(points, instance, rows, piece, infos, vocabulary)
    labels = PanopticLabels(semantic=semantic, instance=instance, instances=instances)
    return MergedLabels(labels=labels, superprimitive=superprimitive, cluster=cluster, seam_joins=joins)


def _join_across_seams(
    groups: _UnionFind,
    halo_point: np.ndarray,  # (H,) primitives labelled in some tile's halo
    halo_piece: np.ndarray,  # (H,) that tile's piece there
    piece: np.ndarray,  # (N,) the owning tile's piece
    piece_class: np.ndarray,
    piece_thing: np.ndarray,
    min_overlap: int,
) -> int:
    """Union the mutual best overlaps of thing pieces of one class; returns how many pairs were joined."""
    owner = piece[halo_point]
    keep = (owner >= 0) & (owner != halo_piece)
    a, b = halo_piece[keep], owner[keep]
    keep = piece_thing[a] & piece_thing[b] & (piece_class[a] == piece_class[b])
    a, b = a[keep], b[keep]
    if a.size == 0:
        return 0
    # Unordered pairs: t's halo over u's core and u's halo over t's core count towards the same pair.
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    pairs, counts = np.unique(np.stack([lo, hi], 1), axis=0, return_counts=True)
    joined = 0
    best = _best_partner(pairs, counts)
    for (p, q), c in zip(pairs.tolist(), counts.tolist()):
        if c >= min_overlap and best.get(p) == q and best.get(q) == p:
            groups.union(p, q)
            joined += 1
    return joined


def _best_partner(pairs: np.ndarray, counts: np.ndarray) -> dict[int, int]:
    """For every piece, the piece it overlaps most (ties: the lower id), over the pairs."""
    best: dict[int, tuple[int, int]] = {}
    for (p, q), c in zip(pairs.tolist(), counts.tolist()):
        for x, y in ((p, q), (q, p)):
            if x not in best or c > best[x][1] or (c == best[x][1] and y < best[x][0]):
                best[x] = (y, c)
    return {x: y for x, (y, _) in best.items()}


def _number_instances(
    groups: _UnionFind,
    piece: np.ndarray,
    piece_class: np.ndarray,
    piece_thing: np.ndarray,
    semantic: np.ndarray,
    is_thing: np.ndarray,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Instance id per primitive and, per instance, the pieces it gathers: things by first primitive, then one
    stuff instance per class (by class index)."""
    n = piece.size
    root = np.array([groups.find(k) for k in range(piece_class.size)], np.int64)
    instance = np.full(n, -1, np.int64)
    rows: list[np.ndarray] = []
    thing_point = (piece >= 0) & piece_thing[np.maximum(piece, 0)] if piece_class.size else np.zeros(n, bool)
    if thing_point.any():
        group_of_point = root[piece[thing_point]]
        ids, first = np.unique(group_of_point, return_index=True)
        order = ids[np.argsort(np.flatnonzero(thing_point)[first], kind="stable")]
        number = np.full(piece_class.size, -1, np.int64)
        number[order] = np.arange(order.size)
        instance[thing_point] = number[group_of_point]
        rows.extend(np.flatnonzero(root == g) for g in order)
    # Every primitive of a stuff class joins its class's one segment, also where its tile found too few of them
    # for a segment of its own: the scene has the segment.
    labelled = semantic >= 0
    stuff_point = labelled & ~is_thing[np.maximum(semantic, 0)] & ~thing_point
    for c in np.unique(semantic[stuff_point]).tolist():
        mask = stuff_point & (semantic == c)
        pieces = np.unique(piece[mask & (piece >= 0)])
        if pieces.size == 0:
            continue  # no tile made a segment of it: its feature and score are unknown
        instance[mask] = len(rows)
        rows.append(pieces)
    return instance, rows


def _instance_infos(
    points: np.ndarray,
    instance: np.ndarray,
    rows: list[np.ndarray],
    piece: np.ndarray,
    infos: list[InstanceInfo],
    vocabulary: Vocabulary,
) -> tuple[InstanceInfo, ...]:
    """One :class:`InstanceInfo` per merged instance: geometry from its primitives, feature and score from its
    pieces weighted by the core primitives each contributes.

    DEPARTURE (docs/method.md §16.3): a piece's feature is its tile's mean over the piece's core and halo.
    """
    if not rows:
        return ()
    labelled = instance >= 0
    core_count = np.bincount(piece[labelled & (piece >= 0)], minlength=len(infos)).astype(np.float64)
    out = []
    order = np.argsort(instance[labelled], kind="stable")
    idx = np.flatnonzero(labelled)[order]
    starts = np.searchsorted(instance[idx], np.arange(len(rows)))
    ends = np.r_[starts[1:], idx.size]
    for k, members in enumerate(rows):
        pts = points[idx[starts[k] : ends[k]]].astype(np.float64)
        weight = core_count[members]
        weight = weight / weight.sum() if weight.sum() > 0 else np.full(len(members), 1.0 / len(members))
        feature = np.sum([w * np.asarray(infos[m].feature, np.float64) for w, m in zip(weight, members)], axis=0)
        feature /= max(float(np.linalg.norm(feature)), 1e-12)
        c = infos[int(members[0])].class_index
        out.append(
            InstanceInfo(
                id=k,
                class_index=c,
                class_name=vocabulary.names[c],
                kind=vocabulary.kinds[c],
                score=float(np.clip(sum(w * infos[m].score for w, m in zip(weight, members)), 0.0, 1.0)),
                num_points=int(pts.shape[0]),
                centroid=pts.mean(axis=0).astype(np.float32),
                bbox_min=pts.min(axis=0).astype(np.float32),
                bbox_max=pts.max(axis=0).astype(np.float32),
                feature=feature.astype(np.float32),
            )
        )
    return tuple(out)
