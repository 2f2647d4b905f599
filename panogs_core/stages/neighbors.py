"""The primitives' k-nearest-neighbour graph: built once, read by the graph cut, the clustering and the labels.

Stages 5 to 8 all walk the same graph (the graph cut's edges, the segments' adjacency, the labels' nearest seen
neighbour), so it is its own stage with its own checkpoint and none of them owns it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from panogs_core.errors import InputError, ShapeError
from panogs_core.io.npz import save_npz
from panogs_core.threads import query_workers


@dataclass(frozen=True)
class KnnGraph:
    """The k nearest neighbours of every point, the point itself excluded."""

    neighbors: np.ndarray  # (N, K) int64, ascending distance
    distances: np.ndarray  # (N, K) float32, metres

    @property
    def k(self) -> int:
        """Neighbours per point K."""
        return int(self.neighbors.shape[1])

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` at exactly ``path``."""
        save_npz(path, neighbors=self.neighbors, distances=self.distances)

    @classmethod
    def load(cls, path: str | Path) -> KnnGraph:
        """Read what :meth:`save` wrote (no pickles)."""
        with np.load(Path(path), allow_pickle=False) as data:
            return cls(neighbors=data["neighbors"].astype(np.int64), distances=data["distances"].astype(np.float32))


def build_knn(points: np.ndarray, k: int) -> KnnGraph:  # points (N, 3) float
    """The ``k`` nearest neighbours of every point, excluding the point itself (scipy cKDTree).

    Duplicate points are handled: the column holding the point's own index is removed, wherever the tree put
    it among the zero-distance ties; if it was not among the first ``k + 1`` the farthest column is dropped.

    Args:
        points: Point positions. ``(N, 3)`` float, metres.
        k: Neighbours per point, self excluded.

    Returns:
        ``neighbors`` ``(N, k)`` int64 and ``distances`` ``(N, k)`` float32, by ascending distance.

    Raises:
        ShapeError: if ``points`` is not ``(N, 3)``.
        InputError: if ``k < 1``, there are fewer than ``k + 1`` points, or coordinates are not finite.

    Example:
        >>> knn = build_knn(np.random.default_rng(0).uniform(size=(50, 3)), 7)
        >>> knn.neighbors.shape, bool((knn.neighbors != np.arange(50)[:, None]).all())
        ((50, 7), True)
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points: expected shape (N, 3), found {points.shape}")
    if k < 1:
        raise InputError(f"k: expected >= 1, found {k}")
    n = points.shape[0]
    if n < k + 1:
        raise InputError(f"points: a {k}-neighbour graph needs at least {k + 1} points, found {n}")
    if not np.isfinite(points).all():
        raise InputError("points: contains NaN or infinite coordinates")
    distances, indices = cKDTree(points).query(points, k=k + 1, workers=query_workers())  # (N, k + 1) each
    is_self = indices == np.arange(n)[:, None]
    drop = is_self.copy()
    drop[~is_self.any(axis=1), -1] = True  # self lost among > k + 1 duplicates: drop the farthest instead
    keep = ~drop
    return KnnGraph(
        neighbors=indices[keep].reshape(n, k).astype(np.int64),
        distances=distances[keep].reshape(n, k).astype(np.float32),
    )
