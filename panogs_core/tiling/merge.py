"""The merge of a tiled run: the tiles' labels as those of one scene (docs/method.md §16.2).

* Each primitive takes its class and instance from the tile whose core holds it.
* A thing instance cut by a seam is one instance: instance a of tile t and instance b of tile u are joined when
  they share a class and each is the other's best overlap (intersection over union) where the two tiles both
  label primitives (t's halo over u's core, u's halo over t's core), with at least ``min_overlap`` shared
  primitives. Joins are transitive (an instance at a corner of four tiles is one).
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
from panogs_core.stages.labeling import PanopticLabels
from panogs_core.types import InstanceInfo, Vocabulary


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
    owner_tile = np.full(n, -1, np.int64)
    infos: list[InstanceInfo] = []  # every tile's instances, piece id = position here
    halo_points, halo_pieces, halo_tiles = [], [], []  # a tile's halo primitives, its piece there, the tile
    offsets = {"sp": 0, "cluster": 0}
    for t, tile in enumerate(tiles):
        base = len(infos)
        infos.extend(tile.instances)
        own = tile.point_index[tile.core]
        owner_tile[own] = t
        semantic[own] = tile.semantic[tile.core]
        piece[own] = _pieces(tile.instance[tile.core], base, t)
        for name, dest, src in (("sp", superprimitive, tile.superprimitive), ("cluster", cluster, tile.cluster)):
            part = src[tile.core]
            dest[own] = np.where(part >= 0, part + offsets[name], -1)
            offsets[name] += int(src.max()) + 1 if src.size else 0
        halo = ~tile.core
        halo_points.append(tile.point_index[halo])
        halo_pieces.append(_pieces(tile.instance[halo], base, t))
        halo_tiles.append(np.full(int(halo.sum()), t, np.int64))
    piece_class = np.array([i.class_index for i in infos], np.int64)
    piece_thing = is_thing[piece_class] if infos else np.zeros(0, bool)
    groups = _UnionFind(len(infos))
    halo_point = np.concatenate(halo_points)
    joins = _join_across_seams(
        groups,
        (np.concatenate(halo_pieces), np.concatenate(halo_tiles)),
        (piece[halo_point], owner_tile[halo_point]),
        piece_class,
        piece_thing,
        min_overlap,
    )
    piece = np.where(piece >= 0, piece, -1)  # the tiles' "no instance" codes: none
    instance, rows = _number_instances(groups, piece, piece_class, piece_thing, semantic, is_thing)
    instances = _instance_infos(points, instance, rows, piece, infos, vocabulary)
    labels = PanopticLabels(semantic=semantic, instance=instance, instances=instances)
    return MergedLabels(labels=labels, superprimitive=superprimitive, cluster=cluster, seam_joins=joins)


def _pieces(local: np.ndarray, base: int, tile: int) -> np.ndarray:
    """Piece ids of a tile's instance ids: ``base + id``, and ``-(1 + tile)`` for its primitives in no instance (so
    that "nothing" in one tile is told apart from "nothing" in another when overlaps are counted)."""
    return np.where(local >= 0, local + base, -1 - tile)


def _join_across_seams(
    groups: _UnionFind,
    halo: tuple[np.ndarray, np.ndarray],  # (H,) piece and tile of every halo primitive of every tile
    owner: tuple[np.ndarray, np.ndarray],  # (H,) piece and tile of the core that holds that primitive
    piece_class: np.ndarray,
    piece_thing: np.ndarray,
    min_overlap: int,
) -> int:
    """Union the thing pieces of one class that are each other's best overlap; returns how many pairs were joined.

    Overlap is the intersection over union on the primitives that both of two tiles label (the halo of each over
    the core of the other): a piece that took in two objects of the other tile is then not every piece's best.
    A piece's best is chosen per neighbouring tile, so an object at the corner of three or four tiles joins each.
    """
    (hp, ht), (op, ot) = halo, owner
    first = ht < ot  # order each entry by tile, so that both directions of a pair of tiles count together
    a, b = np.where(first, hp, op), np.where(first, op, hp)
    ta, tb = np.where(first, ht, ot), np.where(first, ot, ht)
    if a.size == 0:
        return 0
    keys, counts = np.unique(np.stack([a, b, ta, tb], 1), axis=0, return_counts=True)
    # each piece's primitives in the region it shares with the other tile: the sum of its pairs' counts there
    size: dict[tuple[int, int], int] = {}
    for (p, q, tp, tq), c in zip(keys.tolist(), counts.tolist()):
        size[(p, tq)] = size.get((p, tq), 0) + c
        size[(q, tp)] = size.get((q, tp), 0) + c
    candidates = []
    for (p, q, tp, tq), c in zip(keys.tolist(), counts.tolist()):
        if p >= 0 and q >= 0 and piece_thing[p] and piece_thing[q] and piece_class[p] == piece_class[q]:
            candidates.append((p, q, tp, tq, c, c / (size[(p, tq)] + size[(q, tp)] - c)))
    best: dict[tuple[int, int], tuple[float, int]] = {}  # (piece, other tile) -> (IoU, partner)
    for p, q, tp, tq, _, iou in candidates:
        for x, y, other in ((p, q, tq), (q, p, tp)):
            held = best.get((x, other))
            if held is None or iou > held[0] or (iou == held[0] and y < held[1]):
                best[(x, other)] = (iou, y)
    joined = 0
    for p, q, tp, tq, c, _ in candidates:
        if c >= min_overlap and best[(p, tq)][1] == q and best[(q, tp)][1] == p:
            groups.union(p, q)
            joined += 1
    return joined


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
