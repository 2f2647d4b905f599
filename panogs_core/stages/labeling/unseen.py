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
) -> tuple[np.ndarray, dict[str, int]]:  # (N,) int64 classes, how many unseen were labelled how
    """A class for every primitive no key frame saw, and how many were labelled by each rule.

    ``segment``: the majority class of the seen primitives of its super-primitive (the graph cut follows the geometry,
    so an unseen patch of floor under a table is in a floor segment), then ``propagate`` for segments no key frame saw
    at all. ``propagate``: the class of the seen primitive nearest along the kNN graph (edge length = distance), so the
    floor under a bed takes the floor's class across the floor, not the class of the bed 10 cm above it; primitives in
    parts of the graph with no seen primitive take the Euclidean nearest seen one's class. ``field``: the argmax of the
    field's features there (the reference: the field extrapolates). DEPARTURE (the segment's seen majority, not the
    field): docs/method.md §7.5.
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
    if mode == "segment":
        filled = vote_in_segments(classes, segments)
        classes = np.where(unseen, filled, classes)
        counts["segment"] = int((unseen & (classes >= 0)).sum())
        unseen = classes < 0
        if not unseen.any():
            return classes, counts
    n, k = neighbors.shape
    src = np.repeat(np.arange(n), k)
    dst = neighbors.reshape(-1)
    length = np.linalg.norm(points[src] - points[dst], axis=1) + 1e-6  # explicit zeros would drop the edge
    graph = sparse.csr_matrix((length, (src, dst)), shape=(n, n))
    seeds = np.flatnonzero(~unseen)
    _, _, source = csgraph.dijkstra(graph, directed=False, indices=seeds, min_only=True, return_predecessors=True)
    out = classes.copy()
    reached = unseen & (source >= 0)
    out[reached] = classes[source[reached]]
    counts["graph"] = int(reached.sum())
    counts["nearest"] = int((out < 0).sum())
    return fill_nearest_seen(points, out), counts
