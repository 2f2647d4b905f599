"""The simplest answers a 3D panoptic method has to beat.

On held-out real captures they once beat the full method: the argmax of the fused multi-view features per
primitive (no field, no segments), with unseen primitives given their nearest seen primitive's label, and
connected components of that argmax as instances. Every quality table keeps them (``bench/quality.py``). Their
graph tools are ``panogs_core.point_graphs``, which stage 8 uses too: the method never imports its baselines.

- :func:`fused_argmax`: class per primitive from its fused feature; -1 where no key frame saw it.
- :func:`fill_nearest_seen`: unseen primitives take the class of the nearest seen primitive (Euclidean).
- :func:`label_components`: thing primitives of one class within ``radius`` of each other form one instance;
  components under ``min_points`` get no instance; each stuff class is one instance.
"""

from __future__ import annotations

import numpy as np

from panogs_core.point_graphs import radius_pairs, same_label_components

# The instance baseline: "same label within 10 cm, under 100 vertices dropped".
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
