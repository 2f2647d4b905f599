"""A class for every primitive no key frame saw (docs/method.md §7.2): segment, graph or field rules."""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from panogs_core.point_graphs import fill_nearest_seen
from panogs_core.stages.labeling.votes import vote_in_segments


def label_unseen(
    classes: np.ndarray,  # (N,) int64, -1 = no evidence
    field_sims: np.ndarray,  # (N, L)
    points: np.ndarray,  # (N, 3)
    neighbors: np.ndarray,  # (N, K) kNN (self excluded)
    segments: np.ndarray,  # (N,) int64 super-primitive
    mode: str,
    is_thing: np.ndarray | None = None,  # (L,) bool; ``segment-checked`` overrules only stuff segments
    min_normal_cos: float = 0.8,
) -> tuple[np.ndarray, dict[str, int]]:  # (N,) int64 classes, how many unseen were labelled how
    """A class for every primitive no key frame saw, and how many were labelled by each rule.

    ``segment``: the majority class of the seen primitives of its super-primitive (the graph cut follows the geometry,
    so an unseen patch of floor under a table is in a floor segment), then ``propagate`` for segments no key frame saw
    at all. ``segment-checked``: the same, except where the segment's seen part and the unseen primitive are
    different surfaces: in a segment of a stuff class, it takes the class of the seen primitive nearest along the
    kNN graph instead when that is a thing class, the field's own argmax there agrees with it, and the two
    primitives face the same way (normals within ``min_normal_cos``): a thin object set into a wall, whose seen
    part is its own, but not the floor under a table beside a leg, nor a sink whose segment is right.
    ``propagate``: the class of the seen primitive nearest along the kNN graph (edge length = distance), so the floor
    under a bed takes the floor's class across the floor, not the class of the bed 10 cm above it; primitives in
    parts of the graph with no seen primitive take the Euclidean nearest seen one's class. ``field``: the argmax of
    the field's features there (the reference: the field extrapolates). DEPARTURE (the segment's seen majority, not
    the field): docs/method.md §7.5.
    """
    unseen = classes < 0
    counts = {"unseen": int(unseen.sum()), "field": 0, "segment": 0, "graph": 0, "nearest": 0}
    if not unseen.any() or unseen.all():
        return classes.copy(), counts
    if mode == "field":
        out = classes.copy()
        out[unseen] = np.argmax(field_sims[unseen], axis=1)
        counts["field"] = counts["unseen"]
        return out, counts
    out = classes.copy()
    if mode in ("segment", "segment-checked"):
        filled = vote_in_segments(classes, segments)
        by_segment = unseen & (filled >= 0)
        out[by_segment] = filled[by_segment]
        if mode == "segment-checked":
            source = _nearest_seen_along_graph(points, neighbors, unseen)  # from what a key frame saw only
            stuff_segment = by_segment.copy()
            if is_thing is not None:
                stuff_segment &= ~np.asarray(is_thing, bool)[np.maximum(out, 0)]
            overrule = _other_surface(
                out, classes, source, stuff_segment, field_sims, points, neighbors, min_normal_cos
            )
            if is_thing is not None:
                overrule &= np.asarray(is_thing, bool)[np.maximum(classes[source], 0)] & (source >= 0)
            out[overrule] = classes[source[overrule]]
            counts["graph"] += int(overrule.sum())
            by_segment &= ~overrule
        counts["segment"] = int(by_segment.sum())
        unseen = out < 0
        if not unseen.any():
            return out, counts
    source = _nearest_seen_along_graph(points, neighbors, unseen)  # labelled primitives are the seeds
    reached = unseen & (source >= 0)
    out[reached] = out[source[reached]]
    counts["graph"] += int(reached.sum())
    counts["nearest"] = int((out < 0).sum())
    return fill_nearest_seen(points, out), counts


def _nearest_seen_along_graph(
    points: np.ndarray, neighbors: np.ndarray, unseen: np.ndarray
) -> np.ndarray:  # (N,) int64 index of the nearest seen primitive along the kNN graph, -1 where none is reached
    n, k = neighbors.shape
    src = np.repeat(np.arange(n), k)
    dst = neighbors.reshape(-1)
    length = np.linalg.norm(points[src] - points[dst], axis=1) + 1e-6  # explicit zeros would drop the edge
    graph = sparse.csr_matrix((length, (src, dst)), shape=(n, n))
    seeds = np.flatnonzero(~unseen)
    _, _, source = csgraph.dijkstra(graph, directed=False, indices=seeds, min_only=True, return_predecessors=True)
    return np.asarray(source, np.int64)


def _other_surface(
    labelled: np.ndarray,  # (N,) int64 classes with the segment rule applied
    classes: np.ndarray,  # (N,) int64 the seen primitives' classes, -1 unseen
    source: np.ndarray,  # (N,) int64 nearest seen primitive along the graph, -1 none
    candidates: np.ndarray,  # (N,) bool unseen primitives labelled by their segment
    field_sims: np.ndarray,  # (N, L)
    points: np.ndarray,  # (N, 3)
    neighbors: np.ndarray,  # (N, K)
    min_normal_cos: float,
) -> np.ndarray:  # (N,) bool: take the nearest seen primitive's class instead of the segment's
    """Unseen primitives whose nearest seen primitive is of another class than their segment's, which the field
    confirms and whose surface faces the same way as that primitive's."""
    idx = np.flatnonzero(candidates & (source >= 0))
    near_class = classes[source[idx]]
    keep = (near_class != labelled[idx]) & (np.argmax(field_sims[idx], axis=1) == near_class)
    idx = idx[keep]
    out = np.zeros(len(classes), dtype=bool)
    if not len(idx):
        return out
    normals = _local_normals(points, neighbors, np.concatenate([idx, source[idx]]))
    facing = np.abs(np.einsum("md,md->m", normals[: len(idx)], normals[len(idx) :])) >= min_normal_cos
    out[idx[facing]] = True
    return out


def _local_normals(points: np.ndarray, neighbors: np.ndarray, idx: np.ndarray) -> np.ndarray:  # (M, 3) unit
    """The normal of each primitive of ``idx``: the least principal axis of it and its kNN."""
    group = points[np.concatenate([idx[:, None], neighbors[idx]], axis=1)].astype(np.float64)  # (M, K + 1, 3)
    group -= group.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", group, group)  # (M, 3, 3)
    _, vectors = np.linalg.eigh(cov)
    return vectors[:, :, 0]  # eigenvalues ascending: the first axis is the normal
