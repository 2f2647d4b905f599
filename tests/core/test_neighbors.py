"""The primitives' kNN graph: self excluded (also among duplicates), ascending distance, its checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from panogs_core.errors import InputError, ShapeError
from panogs_core.stages.neighbors import KnnGraph, build_knn


class TestBuildKnn:
    def test_smoke(self) -> None:
        points = np.random.default_rng(0).uniform(size=(100, 3)).astype(np.float32)
        knn = build_knn(points, 7)
        assert isinstance(knn, KnnGraph)
        assert knn.neighbors.shape == (100, 7)
        assert knn.neighbors.dtype == np.int64
        assert knn.distances.shape == (100, 7)
        assert knn.distances.dtype == np.float32
        assert knn.k == 7
        assert (np.diff(knn.distances, axis=1) >= 0).all()

    def test_excludes_self(self) -> None:
        points = np.random.default_rng(1).uniform(size=(50, 3))
        knn = build_knn(points, 5)
        assert not (knn.neighbors == np.arange(50)[:, None]).any()
        assert (knn.distances > 0).all()

    def test_excludes_self_with_duplicates(self) -> None:
        rng = np.random.default_rng(2)
        # 12 copies of one point (more than k + 1, so self can fall outside the queried columns), plus pairs.
        points = np.concatenate([np.zeros((12, 3)), np.repeat(rng.uniform(1, 2, (20, 3)), 2, axis=0)])
        knn = build_knn(points, 4)
        assert knn.neighbors.shape == (52, 4)
        assert not (knn.neighbors == np.arange(52)[:, None]).any()
        assert (knn.distances[:12] == 0).all()
        # Each duplicated pair finds its twin first, at distance 0.
        twins = np.arange(12, 52) ^ 1  # (12, 13), (14, 15), ...
        assert (knn.neighbors[12:, 0] == twins).all()
        assert (knn.distances[12:, 0] == 0).all()

    def test_exception(self) -> None:
        with pytest.raises(ShapeError, match="points"):
            build_knn(np.zeros((10, 2)), 3)
        with pytest.raises(InputError, match="at least 8 points"):
            build_knn(np.zeros((5, 3)), 7)
        with pytest.raises(InputError, match="k: expected >= 1"):
            build_knn(np.zeros((5, 3)), 0)
        with pytest.raises(InputError, match="NaN"):
            build_knn(np.full((10, 3), np.nan), 3)

    def test_save_load(self, tmp_path: Path) -> None:
        knn = build_knn(np.random.default_rng(3).uniform(size=(30, 3)), 4)
        knn.save(tmp_path / "neighbors.npz")
        back = KnnGraph.load(tmp_path / "neighbors.npz")
        np.testing.assert_array_equal(back.neighbors, knn.neighbors)
        np.testing.assert_array_equal(back.distances, knn.distances)
        assert (back.neighbors.dtype, back.distances.dtype) == (np.int64, np.float32)
