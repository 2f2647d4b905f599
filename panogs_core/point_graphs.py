"""Graph tools over points that stage 8 (labelling) and the baselines (``evaluation.baselines``) share: pairs of
points within a radius, connected components of one label, and the nearest labelled point.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree


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
