"""The simplest answers a 3D panoptic method has to beat, and the graph helpers they share with stage 8.

Issue 8 measured them on held-out real captures, where they beat the full method: the argmax of the fused
multi-view features per primitive (no field, no segments), with unseen primitives given their nearest seen
primitive's label, and connected components of that argmax as instances. Every quality table keeps them
(``bench/quality.py``), and stage 8 (``labeling.py``) reuses the two graph tools below.

- :func:`fused_argmax`: class per primitive from its fused feature; -1 where no key frame saw it.
- :func:`fill_nearest_seen`: unseen primitives take the class of the nearest seen primitive (Euclidean).
- :func:`label_components`: thing primitives of one class within ``radius`` of each other form one instance;
  components under ``min_points`` get no instance; each stuff class is one instance.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

# The instance baseline of issue 8: "same label within 10 cm, under 100 vertices dropped".
COMPONENT_RADIUS_M = 0.10
COMPONENT_MIN_POINTS = 100


def fused_argmax(
    fused_features: np.ndarray,  # (N, D) mean of unit pixel features, zero rows where unseen
    embeddings: np.ndarray,  # (L, D) text embeddings
) -> np.ndarray:  # (N,) int64 class, -1 where unseen
    """Class of the most similar text embedding to each primitive's fused feature.

    Example:
        >>> fused_argmax(np.array([[0.0, 2.0], [0.0, 0.0]]), np.eye(2)).tolist()
        [1, -1]
    """
    feats = np.asarray(fused_features, np.float32)
    emb = np.asarray(embeddings, np.float32)
    emb = emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12)
    seen = np.einsum("nd,nd->n", feats, feats) > 1e-12
    return np.where(seen, np.argmax(feats @ emb.T, axis=1), -1).astype(np.int64)


def fill_nearest_seen(
    points: np.ndarray,  # (N, 3)
    classes: np.ndarray,  # (N,) int64, -1 = unseen
) -> np.ndarray:  # (N,) int64
    """Each primitive of class -1 takes the class of the nearest primitive with a class (Euclidean).

    Example:
        >>> fill_nearest_seen(np.array([[0.0, 0, 0], [1, 0, 0], [0.2, 0, 0]]), np.array([3, 5, -1])).tolist()
        [3, 5, 3]
    """
    classes = np.asarray(classes, np.int64)
    seen = classes >= 0
    if seen.all() or not seen.any():
        return classes.copy()
    tree = cKDTree(np.asarray(points, np.float64)[seen])
    _, nearest = tree.query(np.asarray(points, np.float64)[~seen], k=1)
    out = classes.copy()
    out[~seen] = classes[seen][nearest]
    return out


def radius_pairs(points: np.ndarray, radius: float) -> np.ndarray:  # (E, 2) int64, i < j
    """Every pair of points closer than ``radius``."""
    return cKDTree(np.asarray(points, np.float64)).query_pairs(radius, output_type="ndarray").astype(np.int64)


def same_label_components(
    labels: np.ndarray,  # (N,) int64, -1 = not part of any component
    pairs: np.ndarray,  # (E, 2) int64 edges
) -> np.ndarray:  # (N,) int64 component id, -1 where labels < 0
    """Connected components of the edges whose two ends carry the same label >= 0."""
    n = labels.size
    keep = (labels[pairs[:, 0]] >= 0) & (labels[pairs[:, 0]] == labels[pairs[:, 1]])
    e = pairs[keep]
    graph = sparse.csr_matrix((np.ones(len(e), np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    _, comp = csgraph.connected_components(graph, directed=False)
    return np.where(labels >= 0, comp, -1).astype(np.int64)


def label_components(
    points: np.ndarray,  # (N, 3)
    semantic: np.ndarray,  # (N,) int64 class, -1 void
    is_thing: np.ndarray,  # (L,) bool
    *,
    radius: float = COMPONENT_RADIUS_M,
    min_points: int = COMPONENT_MIN_POINTS,
    pairs: np.ndarray | None = None,
) -> np.ndarray:  # (N,) int64 instance, -1 none
    """Instances from the semantic labels alone: connected components of each thing class, one per stuff class.

    Args:
        points: Primitive positions.
        semantic: Class per primitive.
        is_thing: Per class, True for thing classes.
        radius: Two primitives of one class closer than this are connected, metres.
        min_points: Thing components with fewer primitives get instance -1.
        pairs: Precomputed :func:`radius_pairs` of ``points`` at ``radius`` (to share between calls).

    Returns:
        Instance ids: thing components by order of their first primitive, then stuff classes by index.

    Example:
        >>> pts = np.array([[0.0, 0, 0], [0.05, 0, 0], [1, 0, 0], [1.05, 0, 0], [3, 0, 0]])
        >>> label_components(pts, np.array([1, 1, 1, 1, 0]), np.array([False, True]), min_points=2).tolist()
        [0, 0, 1, 1, 2]
    """
    semantic = np.asarray(semantic, np.int64)
    is_thing = np.asarray(is_thing, bool)
    thing = (semantic >= 0) & is_thing[np.maximum(semantic, 0)]
    if pairs is None:
        pairs = radius_pairs(points, radius)
    comp = same_label_components(np.where(thing, semantic, -1), pairs)
    instance = np.full(semantic.size, -1, np.int64)
    if thing.any():
        ids, first, counts = np.unique(comp[thing], return_index=True, return_counts=True)
        big = counts >= min_points
        order = ids[big][np.argsort(first[big], kind="stable")]
        number = np.full(int(comp.max()) + 1, -1, np.int64)
        number[order] = np.arange(order.size)
        instance[thing] = number[comp[thing]]
    next_id = int(instance.max()) + 1
    stuff = (semantic >= 0) & ~thing
    for c in np.unique(semantic[stuff]):
        instance[semantic == c] = next_id
        next_id += 1
    return instance
