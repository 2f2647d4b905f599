"""A class for every primitive no key frame saw (docs/method.md §7.2): segment, graph or field rules."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from panogs_core.point_graphs import fill_nearest_seen
from panogs_core.stages.labeling.votes import vote_in_segments


@dataclass(frozen=True)
class NearestSeen:
    """The seen primitive nearest along the kNN graph to every primitive, for one set of unseen ones.

    The first graph search of ``segment-field`` (:func:`label_unseen`) needs only the points, the kNN graph and
    which primitives no key frame saw: the pipeline makes it beside the field's fit, before the labelling.
    """

    unseen: np.ndarray  # (N,) bool the primitives no key frame saw, the search's non-seeds
    source: np.ndarray  # (N,) int64 nearest seen primitive along the graph, -1 where none is reached


def nearest_seen(points: np.ndarray, neighbors: np.ndarray, unseen: np.ndarray) -> NearestSeen:
    """:class:`NearestSeen` of ``points`` ``(N, 3)`` over the kNN ``neighbors`` ``(N, K)``, as the labelling
    converts them (float32 points, int64 neighbours), so that its search gives the same answer to the bit."""
    unseen = np.asarray(unseen, bool)
    pts, nbr = np.asarray(points, np.float32), np.asarray(neighbors, np.int64)
    if not unseen.any() or unseen.all():  # the labelling searches nothing then
        return NearestSeen(unseen, np.full(len(unseen), -1, np.int64))
    return NearestSeen(unseen, _nearest_seen_along_graph(pts, nbr, unseen))


def label_unseen(
    classes: np.ndarray,  # (N,) int64, -1 = no evidence
    field_sims: np.ndarray,  # (N, L)
    points: np.ndarray,  # (N, 3)
    neighbors: np.ndarray,  # (N, K) kNN (self excluded)
    segments: np.ndarray,  # (N,) int64 super-primitive
    mode: str,
    field_margin: float = 0.0,  # ``segment-field``: the field's lead, in cosine units, that overrules a segment
    nearest: NearestSeen | None = None,  # ``segment-field``'s first search, made already (used if for these unseen)
) -> tuple[np.ndarray, dict[str, int]]:  # (N,) int64 classes, how many unseen were labelled how
    """A class for every primitive no key frame saw, and how many were labelled by each rule.

    ``segment``: the majority class of the seen primitives of its super-primitive (the graph cut follows the geometry,
    so an unseen patch of floor under a table is in a floor segment), then ``propagate`` for segments no key frame saw
    at all. ``segment-field``: the same, except where geometry offers two answers and the field picks the other one:
    the segment's seen majority, and the class of the seen primitive nearest along the kNN graph; where they differ,
    the nearest one's class wins when it is the field's own argmax there and leads the segment's class by more than
    ``field_margin``. A thin object set into a wall (its seen part its own, its unseen part in the wall's segment)
    and a wall beside a door (in the door's segment) come out right; the floor under a table beside a seen leg keeps
    the floor's class, where the field says floor. ``propagate``: the class of the seen primitive nearest along the
    kNN graph (edge length = distance), so the floor under a bed takes the floor's class across the floor, not the
    class of the bed 10 cm above it; primitives in parts of the graph with no seen primitive take the Euclidean
    nearest seen one's class. ``field``: the argmax of the field's features there (the reference: the field
    extrapolates). DEPARTURE (the segment's seen majority, checked by the field, not the field): docs/method.md §7.5.
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
    if mode in ("segment", "segment-field"):
        filled = vote_in_segments(classes, segments)
        by_segment = unseen & (filled >= 0)
        out[by_segment] = filled[by_segment]
        if mode == "segment-field":
            if nearest is not None and np.array_equal(nearest.unseen, unseen):
                source = nearest.source
            else:
                source = _nearest_seen_along_graph(points, neighbors, unseen)  # from what a key frame saw only
            overrule = _field_picks_nearest(out, classes, source, by_segment, field_sims, field_margin)
            out[overrule] = classes[source[overrule]]
            counts["field"] = int(overrule.sum())
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


def _field_picks_nearest(
    labelled: np.ndarray,  # (N,) int64 classes with the segment rule applied
    classes: np.ndarray,  # (N,) int64 the seen primitives' classes, -1 unseen
    source: np.ndarray,  # (N,) int64 nearest seen primitive along the graph, -1 none
    candidates: np.ndarray,  # (N,) bool unseen primitives labelled by their segment
    field_sims: np.ndarray,  # (N, L)
    margin: float,
) -> np.ndarray:  # (N,) bool: take the nearest seen primitive's class instead of the segment's
    """Unseen primitives whose nearest seen primitive is of another class than their segment's, where that class is
    the field's argmax and leads the segment's class by more than ``margin``."""
    idx = np.flatnonzero(candidates & (source >= 0))
    near, own = classes[source[idx]], labelled[idx]
    sims = field_sims[idx]
    keep = (near != own) & (np.argmax(sims, axis=1) == near)
    rows = np.arange(len(idx))
    keep &= sims[rows, near] - sims[rows, own] > margin
    out = np.zeros(len(classes), dtype=bool)
    out[idx[keep]] = True
    return out
