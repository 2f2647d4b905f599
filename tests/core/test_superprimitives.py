"""Tests of stage 5: language-guided graph cuts (known-answer scenes and a plain oracle)."""

from __future__ import annotations

import numpy as np
import pytest

from panogs_core.errors import Cancelled, ConfigError, InputError, ShapeError
from panogs_core.stages import superprimitives
from panogs_core.stages.masks import MaskObservations
from panogs_core.stages.neighbors import KnnGraph, build_knn
from panogs_core.stages.superprimitives import (
    SuperPrimitiveConfig,
    SuperPrimitives,
    edge_weights,
    graph_cut_superprimitives,
    split_straddling,
)


def _grid(nu: int, nv: int, spacing: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.arange(nu) * spacing, np.arange(nv) * spacing, indexing="ij")
    return u.ravel(), v.ravel()


def _perpendicular_planes() -> tuple[np.ndarray, np.ndarray]:
    """Floor z=0 (x >= 0.05) and wall x=0 (z >= 0.05), 20 x 20 points each, exact normals."""
    u, v = _grid(20, 20)
    floor = np.c_[u + 0.05, v, np.zeros_like(u)]
    wall = np.c_[np.zeros_like(u), v, u + 0.05]
    points = np.concatenate([floor, wall]).astype(np.float32)
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (400, 1)), np.tile([1.0, 0.0, 0.0], (400, 1))])
    return points, normals.astype(np.float32)


def _coplanar_two_features(dim: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One 40 x 20 plane; the left half has feature e0, the right half e1 (orthogonal)."""
    u, v = _grid(40, 20)
    points = np.c_[u, v, np.zeros_like(u)].astype(np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (points.shape[0], 1))
    features = np.zeros((points.shape[0], dim), np.float32)
    features[u < 1.0, 0] = 1.0
    features[u >= 1.0, 1] = 1.0
    return points, normals, features


def _frames_of_masks(per_frame: list[np.ndarray]) -> MaskObservations:
    """Every point observed in every frame with the given mask id (0 = outside every mask)."""
    index, label, offsets = [], [], [0]
    for ids in per_frame:
        inside = np.flatnonzero(ids > 0)
        index.append(inside.astype(np.int32))
        label.append(np.asarray(ids)[inside].astype(np.int32))
        offsets.append(offsets[-1] + inside.size)
    return MaskObservations(np.array(offsets, np.int64), np.concatenate(index), np.concatenate(label))


def _noisy_cloud(n: int, dim: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    # Few noisy directions (and both signs) so that many edges have small weights and some merges happen.
    directions = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.6, 0.8, 0.0]])
    normals = directions[rng.integers(0, 4, n)] + rng.normal(0, 0.15, (n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    features = rng.normal(size=(3, dim))[rng.integers(0, 3, n)] + rng.normal(0, 0.3, (n, dim))
    features /= np.linalg.norm(features, axis=1, keepdims=True)
    return points, normals.astype(np.float32), features.astype(np.float32)


def _near_threshold_cloud(n: int, dim: int, cos: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat patch whose features put many neighbour dots within ~40 float32 ulps of ``cos``, on both sides.

    Half the rows are one of a few base directions, the others ``c * base + sqrt(1 - c^2) * side`` with ``c``
    a few ulps from ``cos``: a base row next to a mixed row of the same base has a dot right at the threshold.
    """
    rng = np.random.default_rng(seed)
    points = np.c_[rng.uniform(0, 2, (n, 2)), np.zeros(n)].astype(np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (n, 1))
    base = rng.normal(size=(3, dim))[rng.integers(0, 3, n)]
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    side = rng.normal(size=(2, dim))[rng.integers(0, 2, n)]
    side -= np.sum(side * base, axis=1, keepdims=True) * base
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    c = (cos + rng.integers(-40, 41, n) * 2.0**-26)[:, None]
    mixed = np.where(rng.random((n, 1)) < 0.5, base, c * base + np.sqrt(1 - c**2) * side).astype(np.float32)
    return points, normals, mixed / np.linalg.norm(mixed, axis=1, keepdims=True).astype(np.float32)


def _oracle_labels(
    n: int, src: np.ndarray, dst: np.ndarray, weights: np.ndarray, features: np.ndarray | None, cfg
) -> np.ndarray:
    """The reference's segment_graph + small-segment merge written plainly (docs/method.md §4.5-4.7)."""
    parent, rank, size, tau = list(range(n)), [0] * n, [1] * n, [cfg.k_thresh] * n

    def find(x: int) -> int:
        while parent[x] != x:
            x = parent[x]
        return x

    def union(x: int, y: int) -> int:
        if rank[x] > rank[y]:
            parent[y] = x
            size[x] += size[y]
            return x
        parent[x] = y
        size[y] += size[x]
        if rank[x] == rank[y]:
            rank[y] += 1
        return y

    for e in sorted(range(len(weights)), key=lambda i: weights[i]):
        a, b, w = find(int(src[e])), find(int(dst[e])), float(weights[e])
        if a != b and w <= tau[a] and w <= tau[b]:
            if features is None or float(features[a] @ features[b]) > cfg.merge_cosine:
                r = union(a, b)
                tau[r] = w + cfg.k_thresh / size[r]
    for e in range(len(weights)):
        a, b = find(int(src[e])), find(int(dst[e]))
        if a != b and (size[a] < cfg.min_size or size[b] < cfg.min_size):
            union(a, b)
    roots = np.array([find(i) for i in range(n)])
    return np.unique(roots, return_inverse=True)[1]


class TestEdgeWeights:
    def test_matches_per_edge_rule(self) -> None:
        points, normals, features = _noisy_cloud(60, 4, seed=3)
        knn = build_knn(points, 5)
        cfg = SuperPrimitiveConfig(k_neighbors=5)
        src, dst, w = edge_weights(points.astype(np.float64), normals.astype(np.float64), features, knn.neighbors, cfg)
        assert (src == np.repeat(np.arange(60), 5)).all()
        assert (dst == knn.neighbors.ravel()).all()
        for e in range(src.size):
            a, b = src[e], dst[e]
            expected = 1.0 - float(normals[a] @ normals[b])
            d = points[b] - points[a]
            if float(normals[b] @ (d / np.linalg.norm(d))) > 0:
                expected = expected**2
            if 1.0 - float(features[a] @ features[b]) > 0.1:
                expected *= 20.0
            assert w[e] == pytest.approx(expected, rel=1e-5, abs=1e-6)

    @pytest.mark.parametrize("chunk", [1, 3, 64, 2048])
    def test_language_penalty_exact_at_threshold(self, chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
        # Dots that are exactly the float32 values on either side of edge_cosine (a base row e0 against a row
        # (d, sqrt(1 - d^2), 0, ...) dots to d with no rounding): the penalty must fall on exactly the edges below
        # the threshold, whatever the chunking, and an approximate path that skipped one of them would fail here.
        monkeypatch.setattr(superprimitives, "_NEIGHBOR_DOT_CHUNK", chunk)
        cfg = SuperPrimitiveConfig()
        first_similar = np.float32(cfg.edge_cosine - 1e-6)
        while 1.0 - first_similar > np.float32(1.0 - cfg.edge_cosine):
            first_similar = np.nextafter(first_similar, np.float32(2))
        steps = np.arange(-4, 4)  # ulps from the first similar dot: -4..-1 are dissimilar, 0..3 similar
        cosines = first_similar + steps * np.spacing(first_similar)
        rng = np.random.default_rng(11)
        n = 700
        points = np.c_[rng.uniform(0, 2, (n, 2)), np.zeros(n)]
        normals = np.c_[rng.normal(0, 0.1, (n, 2)), np.ones(n)]  # tilted: every edge weighs > 0, the penalty shows
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        pick = rng.integers(0, cosines.size, n)
        features = np.zeros((n, 16), np.float32)
        features[:, 0] = cosines[pick]
        features[:, 1] = np.sqrt(1.0 - cosines[pick].astype(np.float64) ** 2)
        base = rng.random(n) < 0.5
        features[base] = np.eye(16, dtype=np.float32)[0]
        nbrs = build_knn(points, cfg.k_neighbors).neighbors[:, : cfg.k_neighbors]
        _, _, plain = edge_weights(points, normals, None, nbrs, cfg)
        _, _, w = edge_weights(points, normals, features, nbrs, cfg)
        src, dst = np.repeat(np.arange(n), cfg.k_neighbors), nbrs.reshape(-1)
        at = base[src] & ~base[dst]  # these edges' dots are exactly cosines[pick[dst]]
        below = steps[pick[dst[at]]] < 0
        assert (plain > 0).all()
        assert below.any()
        assert not below.all()
        assert np.array_equal(w[at], np.where(below, plain[at] * cfg.language_penalty, plain[at]))

    @pytest.mark.parametrize("chunk", [1, 3, 64, 2048])
    def test_neighbor_dots_do_not_depend_on_chunking(self, chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
        # The float32 bits of every neighbour dot are those of one unchunked einsum: the chunk size is a speed
        # setting only, and no edge near edge_cosine can cross it when the chunk changes.
        monkeypatch.setattr(superprimitives, "_NEIGHBOR_DOT_CHUNK", chunk)
        points, _, features = _near_threshold_cloud(700, 64, 0.9, seed=11)
        nbrs = build_knn(points, 7).neighbors
        expected = np.einsum("nd,nkd->nk", features, features[nbrs])
        assert np.array_equal(superprimitives._neighbor_dots(features, nbrs).view(np.int32), expected.view(np.int32))

    def test_orient_invariant(self) -> None:
        points = np.array([[0, 0, 0], [0.1, 0, 0]], np.float64)
        normals = np.array([[0, 0, 1.0], [0, 0, -1.0]])
        nbrs = np.array([[1], [0]])
        _, _, plain = edge_weights(points, normals, None, nbrs, SuperPrimitiveConfig(k_neighbors=1))
        _, _, inv = edge_weights(
            points, normals, None, nbrs, SuperPrimitiveConfig(k_neighbors=1, orient_invariant=True)
        )
        assert plain.tolist() == [2.0, 2.0]
        assert inv.tolist() == [0.0, 0.0]


class TestGraphCut:
    def test_smoke(self) -> None:
        points, normals = _perpendicular_planes()
        cfg = SuperPrimitiveConfig()
        sp = graph_cut_superprimitives(points, normals, None, build_knn(points, cfg.k_neighbors), cfg)
        assert isinstance(sp, SuperPrimitives)
        assert sp.labels.shape == (800,)
        assert sp.labels.dtype == np.int64

    def test_perpendicular_planes_two_segments(self) -> None:
        points, normals = _perpendicular_planes()
        cfg = SuperPrimitiveConfig()
        sp = graph_cut_superprimitives(points, normals, None, build_knn(points, cfg.k_neighbors), cfg)
        assert sp.count == 2
        assert len(np.unique(sp.labels[:400])) == 1
        assert len(np.unique(sp.labels[400:])) == 1

    def test_language_splits_coplanar_regions(self) -> None:
        points, normals, features = _coplanar_two_features()
        cfg = SuperPrimitiveConfig()
        knn = build_knn(points, cfg.k_neighbors)
        with_language = graph_cut_superprimitives(points, normals, features, knn, cfg)
        without = graph_cut_superprimitives(points, normals, None, knn, cfg)
        switched_off = graph_cut_superprimitives(
            points, normals, features, knn, SuperPrimitiveConfig(use_language=False)
        )
        assert with_language.count == 2
        left = points[:, 0] < 1.0
        assert len(np.unique(with_language.labels[left])) == 1
        assert len(np.unique(with_language.labels[~left])) == 1
        assert without.count == 1
        assert switched_off.count == 1

    def test_masks_split_touching_coplanar_objects(self) -> None:
        # Two desk tops side by side: one plane of one language, one super-primitive to the graph cut. Every
        # mask frame sees the left half in one mask and the right half in another: the masks cut it in two.
        # Without masks, or with the split off, it stays whole.
        points, normals, _ = _coplanar_two_features()
        left = points[:, 0] < 1.0
        masks = _frames_of_masks([np.where(left, 1, 2)] * 3)
        cfg = SuperPrimitiveConfig()
        knn = build_knn(points, cfg.k_neighbors)
        cut = graph_cut_superprimitives(points, normals, None, knn, cfg, masks=masks)
        assert cut.count == 2
        assert len(np.unique(cut.labels[left])) == 1
        assert len(np.unique(cut.labels[~left])) == 1
        assert graph_cut_superprimitives(points, normals, None, knn, cfg).count == 1
        off = SuperPrimitiveConfig(split_purity=0.0)
        assert graph_cut_superprimitives(points, normals, None, knn, off, masks=masks).count == 1

    def test_occasional_part_split_is_not_a_cut(self) -> None:
        # A mask splits the plane in one frame of three (SAM over-segmenting into parts): purity
        # (n / 2 + n + n) / 3n = 0.83 is above split_purity 0.75, so the segment stays whole.
        points, normals, _ = _coplanar_two_features()
        left = points[:, 0] < 1.0
        n = points.shape[0]
        masks = _frames_of_masks([np.where(left, 1, 2), np.ones(n), np.ones(n)])
        cfg = SuperPrimitiveConfig()
        knn = build_knn(points, cfg.k_neighbors)
        assert graph_cut_superprimitives(points, normals, None, knn, cfg, masks=masks).count == 1

    def test_three_objects_in_one_segment_are_cut_twice(self) -> None:
        points, _, _ = _coplanar_two_features()
        third = np.minimum((points[:, 0] / (2.0 / 3.0)).astype(int), 2) + 1  # thirds along x: masks 1, 2, 3
        sp = split_straddling(np.zeros(points.shape[0], np.int64), points, _frames_of_masks([third] * 2), 0.75, 20)
        assert len(np.unique(sp)) == 3
        for k in (1, 2, 3):
            assert len(np.unique(sp[third == k])) == 1

    def test_unobserved_members_follow_their_nearest_observed_neighbour(self) -> None:
        # Only a few columns near each end are ever inside a mask; the middle is never seen in one.
        points, _, _ = _coplanar_two_features()
        x = points[:, 0]
        label = np.where(x < 0.3, 1, np.where(x > 1.6, 2, 0))
        sp = split_straddling(np.zeros(points.shape[0], np.int64), points, _frames_of_masks([label] * 2), 0.75, 20)
        assert len(np.unique(sp)) == 2
        assert len(np.unique(sp[x < 0.9])) == 1
        assert len(np.unique(sp[x > 1.05])) == 1

    def test_orient_invariant_ignores_normal_signs(self) -> None:
        points, normals = _perpendicular_planes()
        flips = np.where(np.random.default_rng(4).random(800) < 0.5, -1.0, 1.0).astype(np.float32)
        flipped = normals * flips[:, None]
        knn = build_knn(points, 7)
        invariant = graph_cut_superprimitives(points, flipped, None, knn, SuperPrimitiveConfig(orient_invariant=True))
        reference = graph_cut_superprimitives(points, flipped, None, knn, SuperPrimitiveConfig())
        assert invariant.count == 2
        assert reference.count > 2  # the reference rule sees w = 2 between opposite signs

    def test_min_size_and_dense_labels(self) -> None:
        points, normals, features = _noisy_cloud(2000, 8, seed=5)
        cfg = SuperPrimitiveConfig()
        sp = graph_cut_superprimitives(points, normals, features, build_knn(points, 7), cfg)
        sizes = np.bincount(sp.labels)
        assert sp.count > 1
        assert sizes.min() >= cfg.min_size
        assert (np.unique(sp.labels) == np.arange(sp.count)).all()

    @pytest.mark.parametrize("language", [True, False])
    def test_matches_plain_oracle(self, language: bool) -> None:
        points, normals, features = _noisy_cloud(1500, 8, seed=6)
        cfg = SuperPrimitiveConfig(min_size=10, small_merge_order="construction")  # the oracle is the reference
        knn = build_knn(points, cfg.k_neighbors)
        feats = features if language else None
        sp = graph_cut_superprimitives(points, normals, feats, knn, cfg)
        src, dst, w = edge_weights(points.astype(np.float64), normals.astype(np.float64), feats, knn.neighbors, cfg)
        expected = _oracle_labels(points.shape[0], src, dst, w, feats, cfg)
        assert sp.count > 5
        assert (sp.labels == expected).all()

    def test_merge_check_exact_at_threshold(self) -> None:
        # Root pairs whose dots sit within a few ulps of merge_cosine: the FH merge decides as the oracle's
        # ``features[a] @ features[b]`` does.
        points, normals, features = _near_threshold_cloud(1500, 64, 0.9, seed=12)
        cfg = SuperPrimitiveConfig(k_thresh=5.0, min_size=1, small_merge_order="construction")
        knn = build_knn(points, cfg.k_neighbors)
        sp = graph_cut_superprimitives(points, normals, features, knn, cfg)
        src, dst, w = edge_weights(points.astype(np.float64), normals.astype(np.float64), features, knn.neighbors, cfg)
        assert 1 < sp.count < points.shape[0] // 2
        assert (sp.labels == _oracle_labels(points.shape[0], src, dst, w, features, cfg)).all()

    @pytest.mark.parametrize("order", ["weight", "language"])
    def test_small_merge_orders_leave_no_small_segment(self, order: str) -> None:
        points, normals, features = _noisy_cloud(1500, 8, seed=6)
        cfg = SuperPrimitiveConfig(min_size=10, small_merge_order=order)  # type: ignore[arg-type]
        sp = graph_cut_superprimitives(points, normals, features, build_knn(points, cfg.k_neighbors), cfg)
        assert np.bincount(sp.labels).min() >= cfg.min_size
        assert (np.unique(sp.labels) == np.arange(sp.count)).all()

    def test_language_small_merge_joins_closest_language(self) -> None:
        # A 3-point piece (no FH merge: its normals disagree with everything) between a "floor" segment and a
        # "chair" segment; its features are the chair's, so it joins the chair, whatever the edge order.
        floor = np.c_[np.arange(10) * 0.05, np.zeros(10), np.zeros(10)]
        piece = np.c_[0.5 + np.arange(3) * 0.05, np.zeros(3), np.zeros(3)]
        chair = np.c_[0.65 + np.arange(10) * 0.05, np.zeros(10), np.zeros(10)]
        points = np.concatenate([floor, piece, chair])
        normals = np.repeat([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [10, 3, 10], axis=0)
        features = np.repeat(np.eye(2, dtype=np.float32), [10, 13], axis=0)
        knn = build_knn(points, 2)
        cfg = SuperPrimitiveConfig(k_neighbors=2, min_size=5, small_merge_order="language")
        labels = graph_cut_superprimitives(points, normals, features, knn, cfg).labels
        assert labels.tolist() == [0] * 10 + [1] * 13

    def test_small_merge_order_validated(self) -> None:
        with pytest.raises(ConfigError, match="small_merge_order"):
            SuperPrimitiveConfig(small_merge_order="random")  # type: ignore[arg-type]

    def test_uses_first_k_columns(self) -> None:
        points, normals, features = _noisy_cloud(500, 8, seed=7)
        cfg = SuperPrimitiveConfig(k_neighbors=5)
        wide = graph_cut_superprimitives(points, normals, features, build_knn(points, 9), cfg)
        exact = graph_cut_superprimitives(points, normals, features, build_knn(points, 5), cfg)
        assert (wide.labels == exact.labels).all()

    def test_progress_and_cancel(self) -> None:
        points, normals = _perpendicular_planes()
        knn = build_knn(points, 7)
        calls: list[tuple[int, int]] = []
        graph_cut_superprimitives(
            points, normals, None, knn, SuperPrimitiveConfig(), on_progress=lambda d, t: calls.append((d, t))
        )
        assert calls
        assert calls[-1][0] == calls[-1][1]

        def cancel(done: int, total: int) -> None:
            raise Cancelled("stop")

        with pytest.raises(Cancelled):
            graph_cut_superprimitives(points, normals, None, knn, SuperPrimitiveConfig(), on_progress=cancel)

    def test_save_load(self, tmp_path) -> None:
        sp = SuperPrimitives(labels=np.array([0, 1, 1, 2], np.int64))
        sp.save(tmp_path / "sp")  # exactly this path, no ".npz" appended
        loaded = SuperPrimitives.load(tmp_path / "sp")
        assert loaded.count == 3
        assert (loaded.labels == sp.labels).all()

    def test_exception(self) -> None:
        points, normals = _perpendicular_planes()
        knn = build_knn(points, 7)
        cfg = SuperPrimitiveConfig()
        with pytest.raises(ShapeError, match="normals"):
            graph_cut_superprimitives(points, normals[:10], None, knn, cfg)
        with pytest.raises(ShapeError, match="features"):
            graph_cut_superprimitives(points, normals, np.zeros((10, 4), np.float32), knn, cfg)
        bad = KnnGraph(neighbors=knn.neighbors.copy(), distances=knn.distances)
        bad.neighbors[0, 0] = 800
        with pytest.raises(InputError, match="indices"):
            graph_cut_superprimitives(points, normals, None, bad, cfg)
        with pytest.raises(InputError, match="k_neighbors"):
            graph_cut_superprimitives(points, normals, None, build_knn(points, 3), cfg)


class TestConfig:
    @pytest.mark.parametrize(
        ("field", "value"),
        [
            ("k_neighbors", 0),
            ("k_thresh", 0.0),
            ("language_penalty", 0.5),
            ("edge_cosine", 1.5),
            ("merge_cosine", -2.0),
            ("min_size", 0),
        ],
    )
    def test_exception_names_field(self, field: str, value: float) -> None:
        with pytest.raises(ConfigError, match=f"superprimitives.{field}"):
            SuperPrimitiveConfig(**{field: value})
