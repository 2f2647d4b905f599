"""Panoptic assembly (docs/method.md §7): thing instances from the clusters (whole, split by class, or connected
components), one instance per stuff class, and the instance table's rows."""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from panogs_core.point_graphs import same_label_components
from panogs_core.stages.labeling.config import LabelingConfig
from panogs_core.stages.labeling.votes import majority
from panogs_core.types import InstanceInfo, Vocabulary


def assemble(
    cls: np.ndarray, cluster: np.ndarray, is_thing: np.ndarray, min_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Semantic (N,), instance (N,) and the class of each instance (I,); see ``assign_panoptic``."""
    thing = (cls >= 0) & is_thing[np.maximum(cls, 0)]
    semantic = cls.copy()
    instance = np.full(cls.shape, -1, np.int64)
    # DEPARTURE (each cluster's thing points: one instance of their majority thing class): docs/method.md §7.5.
    member = thing & (cluster >= 0)
    thing_classes = np.zeros(0, np.int64)
    if member.any():
        clu, major, _, size = majority(cluster[member], cls[member])
        big = size >= min_points
        thing_classes = major[big]
        inst_of_cluster = np.full(int(cluster.max()) + 1, -1, np.int64)
        inst_of_cluster[clu[big]] = np.arange(int(big.sum()))
        inst = np.where(member, inst_of_cluster[np.maximum(cluster, 0)], -1)
        instance[inst >= 0] = inst[inst >= 0]
        semantic[inst >= 0] = thing_classes[inst[inst >= 0]]
    # DEPARTURE (one instance per stuff class, whatever the cluster): docs/method.md §7.5.
    stuff = (cls >= 0) & ~thing
    stuff_size = np.bincount(cls[stuff], minlength=len(is_thing))
    stuff_classes = np.flatnonzero((stuff_size >= min_points) & ~is_thing)
    inst_of_class = np.full(len(is_thing), -1, np.int64)
    inst_of_class[stuff_classes] = len(thing_classes) + np.arange(len(stuff_classes))
    instance[stuff] = inst_of_class[cls[stuff]]
    return semantic, instance, np.concatenate([thing_classes, stuff_classes]).astype(np.int64)


def assemble_split(
    cls: np.ndarray, cluster: np.ndarray, is_thing: np.ndarray, min_points: int, neighbors: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_assemble`` with thing instances split by class inside a cluster.

    1. The thing primitives of one (cluster, class) are cut into kNN-connected components; a component of at
       least ``min_points`` primitives is an instance of that class.
    2. Smaller components join the instance of their own class they share the most kNN edges with (in rounds,
       so fragments chain); e.g. chair-leg primitives left in the floor's cluster rejoin their chair.
    3. What is left joins the largest instance of its cluster, taking its class (class noise inside one
       object, as ``_assemble`` does); in a cluster without one, the (cluster, class) remainder is an
       instance if it has ``min_points`` primitives, else it keeps its class and gets no instance.
    Stuff: one instance per class, as in ``_assemble``.
    """
    n, num_classes = cls.size, len(is_thing)
    thing = (cls >= 0) & is_thing[np.maximum(cls, 0)]
    member = thing & (cluster >= 0)
    semantic = cls.copy()
    instance = np.full(n, -1, np.int64)
    key = np.where(member, np.maximum(cluster, 0) * num_classes + np.maximum(cls, 0), -1)  # (N,)
    nbr = neighbors[:, : min(neighbors.shape[1], 64)]
    src = np.repeat(np.arange(n), nbr.shape[1])
    dst = nbr.reshape(-1)
    same = (key[src] >= 0) & (key[src] == key[dst])
    graph = sparse.csr_matrix((np.ones(int(same.sum()), np.int8), (src[same], dst[same])), shape=(n, n))
    _, comp = csgraph.connected_components(graph, directed=True, connection="weak")
    comp = np.where(member, comp, -1)
    comp_size = np.bincount(comp[member], minlength=int(comp.max()) + 1 if member.any() else 0)
    big = member & (comp_size[np.maximum(comp, 0)] >= min_points)
    # 1. big components -> instances, numbered by (cluster, first primitive) so ids follow cluster order
    big_comps = np.unique(comp[big])
    first = np.full(comp_size.size, n, np.int64)
    np.minimum.at(first, comp[big], np.flatnonzero(big))
    order = big_comps[np.lexsort((first[big_comps], cluster[first[big_comps]]))]
    inst_of_comp = np.full(comp_size.size, -1, np.int64)
    inst_of_comp[order] = np.arange(order.size)
    inst_class = cls[first[order]].tolist()
    instance[big] = inst_of_comp[comp[big]]
    # 2. small components adopt the adjacent instance of their class with the most kNN edges
    for _ in range(8):
        left = member & (instance < 0)
        edge = left[src] & (instance[dst] >= 0)
        if not edge.any():
            break
        target = instance[dst[edge]]
        ok = np.asarray(inst_class, np.int64)[target] == cls[src[edge]]
        if not ok.any():
            break
        c, t = comp[src[edge][ok]], target[ok]
        pairs, counts = np.unique(np.stack([c, t], 1), axis=0, return_counts=True)
        best = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))
        best = best[np.r_[True, pairs[best, 0][1:] != pairs[best, 0][:-1]]]
        adopt = np.full(comp_size.size, -1, np.int64)
        adopt[pairs[best, 0]] = pairs[best, 1]
        instance[left] = adopt[comp[left]]
    # 3. the rest: a (cluster, class) instance of its own if big enough, else the cluster's largest instance
    rest = member & (instance < 0)
    if rest.any():
        keys, inverse, counts = np.unique(key[rest], return_inverse=True, return_counts=True)
        own = counts >= min_points
        new = np.where(own, len(inst_class) + np.cumsum(own) - 1, -1)
        instance[rest] = new[inverse.reshape(-1)]
        inst_class += (keys[own] % num_classes).tolist()
        left = member & (instance < 0)
        has = instance >= 0
        if left.any() and has.any():
            sizes = np.bincount(instance[has], minlength=len(inst_class))
            largest = np.full(int(cluster.max()) + 1, -1, np.int64)
            by_size = np.flatnonzero(has)[np.argsort(sizes[instance[has]], kind="stable")]
            largest[cluster[by_size]] = instance[by_size]  # ascending size: the largest is written last
            instance[left] = largest[cluster[left]]
    thing_classes = np.asarray(inst_class, np.int64)
    semantic[instance >= 0] = thing_classes[instance[instance >= 0]]
    stuff = (cls >= 0) & ~thing
    stuff_size = np.bincount(cls[stuff], minlength=num_classes)
    stuff_classes = np.flatnonzero((stuff_size >= min_points) & ~is_thing)
    inst_of_class = np.full(num_classes, -1, np.int64)
    inst_of_class[stuff_classes] = len(thing_classes) + np.arange(len(stuff_classes))
    instance[stuff] = inst_of_class[cls[stuff]]
    return semantic, instance, np.concatenate([thing_classes, stuff_classes]).astype(np.int64)


def assemble_components(
    cls: np.ndarray,
    cluster: np.ndarray,
    is_thing: np.ndarray,
    points: np.ndarray,
    neighbors: np.ndarray,
    cfg: LabelingConfig,
    seen: np.ndarray | None = None,  # (N,) bool primitives some key frame saw; None = all
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thing instances from connected components of the classes, split by the clusters where they agree.

    DEPARTURE (the classes draw the instances, the clusters only split them; docs/method.md §7.5). As in the
    baseline (``evaluation.baselines.label_components``: one class, kNN edges up to ``component_radius``), and
    the clusters only split a component where touching objects of one class stand together (a row of chairs, a
    run of bookshelves), which the classes alone cannot separate:

    1. ``instances="components"``: each component of at least ``min_instance_points`` primitives is an instance.
    2. ``instances="hybrid"``: a component is split when two or more of its clusters are large parts of it
       (``split_min_points`` primitives and ``split_min_fraction`` of the component each); the primitives of
       its small clusters join the large part nearest along the component's edges. A cluster that is a
       small part of an object (a chair's leg, a cushion seen apart by SAM) never splits it. The sizes count
       ``seen`` primitives only: a cluster is evidence of an object of its own only where the masks saw it, and
       the unseen part of a bathtub that few key frames saw, clustered apart for want of masks, is no second tub.

    Stuff: one instance per class, as in ``_assemble``.
    """
    n, num_classes = cls.size, len(is_thing)
    thing = (cls >= 0) & is_thing[np.maximum(cls, 0)]
    k = neighbors.shape[1]
    src = np.repeat(np.arange(n), k)
    dst = neighbors.reshape(-1)
    near = np.linalg.norm(points[src] - points[dst], axis=1) <= cfg.component_radius
    edges = np.stack([src[near], dst[near]], 1)
    comp = same_label_components(np.where(thing, cls, -1), edges)  # (N,) -1 off things
    instance = np.full(n, -1, np.int64)
    if thing.any():
        owner = comp.copy()  # the unit that becomes an instance: a component, or one large part of it
        if cfg.instances == "hybrid":
            evidence = np.ones(n, bool) if seen is None else np.asarray(seen, bool)
            owner = _split_by_clusters(comp, cluster, edges, cfg.split_min_points, cfg.split_min_fraction, evidence)
        ids, first, counts = np.unique(owner[thing], return_index=True, return_counts=True)
        big = counts >= cfg.min_instance_points
        order = ids[big][np.argsort(np.flatnonzero(thing)[first[big]], kind="stable")]
        number = np.full(int(owner.max()) + 1, -1, np.int64)
        number[order] = np.arange(order.size)
        instance[thing] = number[owner[thing]]
        thing_classes = np.zeros(order.size, np.int64)
        thing_classes[instance[thing & (instance >= 0)]] = cls[thing & (instance >= 0)]
    else:
        thing_classes = np.zeros(0, np.int64)
    stuff = (cls >= 0) & ~thing
    stuff_size = np.bincount(cls[stuff], minlength=num_classes)
    stuff_classes = np.flatnonzero((stuff_size >= cfg.min_instance_points) & ~is_thing)
    inst_of_class = np.full(num_classes, -1, np.int64)
    inst_of_class[stuff_classes] = len(thing_classes) + np.arange(len(stuff_classes))
    instance[stuff] = inst_of_class[cls[stuff]]
    return cls.copy(), instance, np.concatenate([thing_classes, stuff_classes]).astype(np.int64)


def _split_by_clusters(
    comp: np.ndarray,  # (N,) int64 component, -1 = not a thing primitive
    cluster: np.ndarray,  # (N,) int64 cluster, -1 = removed
    edges: np.ndarray,  # (E, 2) int64 graph edges
    min_points: int,
    min_fraction: float,
    seen: np.ndarray,  # (N,) bool: only these count towards a part's size
) -> np.ndarray:  # (N,) int64 owner id, -1 where comp is -1
    """Per primitive, its component, or the large cluster part of its component it belongs to or is nearest."""
    n = comp.size
    member = comp >= 0
    span = int(cluster.max()) + 2
    part = np.where(member, comp * span + (cluster + 1), -1)  # (component, cluster) key
    keys, inverse = np.unique(part[member], return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse, weights=seen[member], minlength=len(keys))  # seen primitives per part
    comp_of_key = keys // span
    comp_size = np.bincount(comp[member], weights=seen[member])
    large = (counts >= max(min_points, 1)) & (counts >= min_fraction * comp_size[comp_of_key])
    splits = np.bincount(comp_of_key[large], minlength=comp_size.size) >= 2
    owner = np.where(member, comp, -1)
    split_member = member & splits[np.maximum(comp, 0)]
    if not split_member.any():
        return owner
    key_of = np.full(n, -1, np.int64)
    key_of[member] = inverse
    is_large = split_member & large[np.maximum(key_of, 0)]
    # New owner ids above every component id: one per large part.
    base = int(comp.max()) + 1
    owner[is_large] = base + key_of[is_large]
    # Small parts of a split component: the large part nearest along the component's own edges.
    inside = split_member[edges[:, 0]] & (comp[edges[:, 0]] == comp[edges[:, 1]])
    e = edges[inside]
    graph = sparse.csr_matrix((np.ones(len(e), np.float32), (e[:, 0], e[:, 1])), shape=(n, n))
    seeds = np.flatnonzero(is_large)
    _, _, source = csgraph.dijkstra(graph, directed=False, indices=seeds, min_only=True, return_predecessors=True)
    rest = split_member & ~is_large
    reached = rest & (source >= 0)
    owner[reached] = owner[source[reached]]
    return owner


def instance_infos(
    points: np.ndarray,
    feats: np.ndarray,
    logits: np.ndarray,
    instance: np.ndarray,
    inst_class: np.ndarray,
    vocabulary: Vocabulary,
) -> tuple[InstanceInfo, ...]:
    num = len(inst_class)
    if num == 0:
        return ()
    idx = np.flatnonzero(instance >= 0)
    ins = instance[idx]
    counts = np.bincount(ins, minlength=num).astype(np.float64)
    sums = np.stack([np.bincount(ins, weights=points[idx, a], minlength=num) for a in range(3)], 1)
    centroid = sums / counts[:, None]
    # A sparse (I, N) membership product sums features without copying the (N, D) array.
    member = sparse.csr_matrix((np.ones(len(idx), np.float32), (ins, idx)), shape=(num, len(instance)))
    mean_feat = np.asarray(member @ feats, dtype=np.float64)
    mean_feat /= np.maximum(np.linalg.norm(mean_feat, axis=1, keepdims=True), 1e-12)
    # Score: softmax probability of the instance's class at each of its points, averaged.
    log_norm = np.logaddexp.reduce(logits[idx].astype(np.float64), axis=1)
    prob = np.exp(logits[idx, inst_class[ins]] - log_norm)
    score = np.bincount(ins, weights=prob, minlength=num) / counts
    order = np.argsort(ins, kind="stable")
    starts = np.r_[0, np.cumsum(counts.astype(np.int64))[:-1]]
    sorted_pts = points[idx[order]]
    lo, hi = np.minimum.reduceat(sorted_pts, starts), np.maximum.reduceat(sorted_pts, starts)
    return tuple(
        InstanceInfo(
            id=k,
            class_index=int(c),
            class_name=vocabulary.names[c],
            kind=vocabulary.kinds[c],
            score=float(np.clip(score[k], 0.0, 1.0)),
            num_points=int(counts[k]),
            centroid=centroid[k].astype(np.float32),
            bbox_min=lo[k].astype(np.float32),
            bbox_max=hi[k].astype(np.float32),
            feature=mean_feat[k].astype(np.float32),
        )
        for k, c in enumerate(inst_class)
    )
