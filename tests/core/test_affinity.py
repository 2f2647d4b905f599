"""Stage 6: segment pairs and the JSD affinity, against hand values and a slow oracle."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

import panogs_core.stages.affinity as affinity_module
from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.stages.affinity import (
    AffinityConfig,
    MaskHistograms,
    edge_affinity,
    segment_adjacency,
)
from panogs_core.stages.masks import MaskObservations
from panogs_core.stages.neighbors import KnnGraph

LN2 = math.log(2.0)

MEAN = AffinityConfig(aggregate="mean")  # the reference's weighted mean (docs/method.md §5.4)


def _knn(neighbors: list[list[int]] | np.ndarray) -> KnnGraph:
    nbrs = np.asarray(neighbors, dtype=np.int64)
    return KnnGraph(neighbors=nbrs, distances=np.ones(nbrs.shape, dtype=np.float32))


def _observations(frames: list[list[tuple[int, int]]]) -> MaskObservations:
    """Frames as lists of (point, mask id) pairs; mask id 0 entries are dropped as observe_masks does."""
    kept = [[(p, m) for p, m in frame if m > 0] for frame in frames]
    sizes = [len(frame) for frame in kept]
    flat = [item for frame in kept for item in frame]
    return MaskObservations(
        offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        point_index=np.array([p for p, _ in flat], dtype=np.int32).reshape(-1),
        label=np.array([m for _, m in flat], dtype=np.int32).reshape(-1),
    )


def _naive_affinity(labels: np.ndarray, pairs: np.ndarray, obs: MaskObservations) -> np.ndarray:
    """The oracle: a plain loop over pairs and frames, JSD over the union of labels, as in the paper."""
    sizes = Counter(labels.tolist())
    out = []
    for i, j in pairs.tolist():
        num = den = 0.0
        for v in range(obs.num_frames):
            lo, hi = obs.offsets[v], obs.offsets[v + 1]
            seen = list(zip(obs.point_index[lo:hi].tolist(), obs.label[lo:hi].tolist(), strict=True))
            hist_i = Counter(m for p, m in seen if labels[p] == i and m > 0)
            hist_j = Counter(m for p, m in seen if labels[p] == j and m > 0)
            n_i, n_j = sum(hist_i.values()), sum(hist_j.values())
            if n_i == 0 or n_j == 0:
                continue
            jsd = 0.0
            for m in set(hist_i) | set(hist_j):
                p, q = hist_i[m] / n_i, hist_j[m] / n_j
                mid = (p + q) / 2
                jsd += 0.5 * (p * math.log(p / mid) if p else 0.0) + 0.5 * (q * math.log(q / mid) if q else 0.0)
            weight = (n_i / sizes[i]) * (n_j / sizes[j])
            num += (1.0 - jsd) * weight
            den += weight
        out.append(num / den if den > 0 else 0.0)
    return np.array(out)


def _random_case(seed: int, num_points: int = 400, num_segments: int = 30, num_frames: int = 9):
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, num_segments, num_points)
    frames = []
    for _ in range(num_frames):
        seen = np.flatnonzero(rng.random(num_points) < rng.uniform(0.1, 0.9))
        # Mostly one id per segment with noise, so distributions overlap partly: the interesting case.
        ids = np.where(rng.random(seen.size) < 0.7, labels[seen] % 5 + 1, rng.integers(0, 6, seen.size))
        frames.append(list(zip(seen.tolist(), ids.tolist(), strict=True)))
    pairs = np.array([(i, j) for i in range(num_segments) for j in range(i + 1, num_segments)])
    pairs = pairs[rng.random(len(pairs)) < 0.3]
    return labels, pairs, _observations(frames)


class TestAffinityConfig:
    def test_smoke(self) -> None:
        cfg = AffinityConfig()
        assert cfg.mode == "jsd"
        assert cfg.min_covisibility == 0.0

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"mode": "cosine"}, r"affinity\.mode: expected 'jsd' or 'language', found 'cosine'"),
            ({"min_covisibility": -1.0}, r"affinity\.min_covisibility: expected a number >= 0"),
            ({"min_covisibility": math.nan}, r"affinity\.min_covisibility"),
            ({"eps": 0.0}, r"affinity\.eps: expected a number > 0, found 0\.0"),
            ({"chunk_rows": 0}, r"affinity\.chunk_rows: expected an integer >= 1, found 0"),
            ({"chunk_rows": True}, r"affinity\.chunk_rows"),
        ],
    )
    def test_exception(self, kwargs: dict, match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            AffinityConfig(**kwargs)


class TestSegmentAdjacency:
    def test_feature(self) -> None:
        labels = np.array([0, 0, 1, 2, 2, -1])
        knn = _knn([[1, 2], [0, 2], [3, 0], [4, 2], [3, 5], [4, -1]])
        pairs, edges = segment_adjacency(labels, knn)
        np.testing.assert_array_equal(pairs, [[0, 1], [1, 2]])
        np.testing.assert_array_equal(edges, [3, 2])  # 0->2, 1->2, 2->0 ; 2->3, 3->2

    def test_cardinality(self) -> None:
        rng = np.random.default_rng(1)
        labels = rng.integers(0, 20, 300)
        pairs = segment_adjacency(labels, _knn(rng.integers(0, 300, (300, 6))))[0]
        assert pairs.dtype == np.int64
        assert pairs.shape[1] == 2
        assert np.all(pairs[:, 0] < pairs[:, 1])
        assert len({tuple(p) for p in pairs.tolist()}) == len(pairs)

    def test_exception(self) -> None:
        with pytest.raises(ShapeError, match=r"knn.neighbors must be \(3, K\) to match labels, found \(2, 1\)"):
            segment_adjacency(np.zeros(3, np.int64), _knn([[1], [0]]))


class TestEdgeAffinity:
    def _two_segments(self, frames: list[list[tuple[int, int]]], size: int = 4) -> np.ndarray:
        labels = np.repeat([0, 1], size)
        return edge_affinity(labels, np.array([[0, 1]]), _observations(frames), AffinityConfig())

    def test_identical_is_one(self) -> None:
        aff = self._two_segments([[(0, 3), (1, 3), (2, 7), (3, 7), (4, 3), (5, 3), (6, 7), (7, 7)]])
        assert aff.dtype == np.float32
        assert aff[0] == pytest.approx(1.0, abs=1e-6)

    def test_disjoint_is_one_minus_ln2(self) -> None:
        aff = self._two_segments([[(0, 3), (1, 3), (2, 3), (3, 3), (4, 5), (5, 5), (6, 5), (7, 5)]])
        assert aff[0] == pytest.approx(1.0 - LN2, abs=1e-6)

    def test_partial_overlap(self) -> None:
        # p = (1, 0), q = (1/2, 1/2): JSD = 1/2 [ln(4/3)] + 1/2 [1/2 ln(2/3) + 1/2 ln 2].
        aff = self._two_segments([[(0, 3), (1, 3), (2, 3), (3, 3), (4, 3), (5, 3), (6, 5), (7, 5)]])
        jsd = 0.5 * math.log(4 / 3) + 0.5 * (0.5 * math.log(2 / 3) + 0.5 * LN2)
        assert aff[0] == pytest.approx(1.0 - jsd, abs=1e-6)

    def test_never_co_observed_is_zero(self) -> None:
        aff = self._two_segments([[(0, 3), (1, 3)], [(5, 4), (6, 4)], []])
        assert aff[0] == 0.0

    def test_visibility_weighting(self) -> None:
        # Frame 0: both fully seen, identical (s = 1, c = 1). Frame 1: segment 0 barely seen (1 of 10),
        # disjoint (s = 1 - ln 2, c = 0.1). The barely-seen frame counts a tenth.
        labels = np.repeat([0, 1], 10)
        frame0 = [(p, 1) for p in range(20)]
        frame1 = [(0, 2)] + [(p, 3) for p in range(10, 20)]
        aff = edge_affinity(labels, np.array([[0, 1]]), _observations([frame0, frame1]), MEAN)
        expected = (1.0 * 1.0 + (1.0 - LN2) * 0.1) / (1.0 + 0.1)
        assert aff[0] == pytest.approx(expected, abs=1e-6)
        # The weighted median follows the frame that holds most of the weight.
        median = edge_affinity(labels, np.array([[0, 1]]), _observations([frame0, frame1]), AffinityConfig())
        assert median[0] == pytest.approx(1.0)

    def test_median_ignores_a_minority_of_merged_frames(self) -> None:
        # Two segments in different masks in 3 frames and in one merged mask in 1 (SAM under-segmenting):
        # the mean is (3 (1 - ln 2) + 1) / 4 = 0.48, the median stays at 1 - ln 2.
        labels = np.repeat([0, 1], 10)
        apart = [(p, 1 + (p >= 10)) for p in range(20)]
        merged = [(p, 1) for p in range(20)]
        obs = _observations([apart, apart, merged, apart])
        pair = np.array([[0, 1]])
        assert edge_affinity(labels, pair, obs, MEAN)[0] == pytest.approx((3 * (1 - LN2) + 1) / 4, abs=1e-6)
        assert edge_affinity(labels, pair, obs, AffinityConfig())[0] == pytest.approx(1 - LN2, abs=1e-6)

    def test_min_covisibility(self) -> None:
        labels = np.repeat([0, 1], 10)
        frame = [(0, 1), (10, 1)]  # c = 0.1 * 0.1
        obs = _observations([frame])
        assert edge_affinity(labels, np.array([[0, 1]]), obs, AffinityConfig())[0] == pytest.approx(1.0)
        strict = AffinityConfig(min_covisibility=0.05)
        assert edge_affinity(labels, np.array([[0, 1]]), obs, strict)[0] == 0.0

    def test_symmetric(self) -> None:
        labels, pairs, obs = _random_case(3)
        cfg = AffinityConfig()
        np.testing.assert_array_equal(
            edge_affinity(labels, pairs, obs, cfg), edge_affinity(labels, pairs[:, ::-1], obs, cfg)
        )

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_matches_naive_oracle(self, seed: int) -> None:
        labels, pairs, obs = _random_case(seed)
        fast = edge_affinity(labels, pairs, obs, MEAN)
        np.testing.assert_allclose(fast, _naive_affinity(labels, pairs, obs), atol=2e-6)
        assert np.all((fast == 0) | ((fast >= 1 - LN2 - 1e-6) & (fast <= 1 + 1e-6)))

    def test_chunking_does_not_change_result(self) -> None:
        labels, pairs, obs = _random_case(4)
        whole = edge_affinity(labels, pairs, obs, AffinityConfig())
        chunked = edge_affinity(labels, pairs, obs, AffinityConfig(chunk_rows=5))
        np.testing.assert_allclose(chunked, whole, atol=1e-7)

    def test_large_mask_ids(self, monkeypatch: pytest.MonkeyPatch) -> None:
        # Keys that would not fit an int64 force the dense renumbering of mask ids; values must not change.
        # Such scenes need ~1e9 (segment, frame) slots, so the limit is lowered instead.
        monkeypatch.setattr(affinity_module, "_KEY_LIMIT", 10_000)
        labels, pairs, obs = _random_case(5)
        huge = (obs.label.astype(np.int64) * 1000 + 2**31 - 6000).astype(np.int32)
        big = MaskObservations(offsets=obs.offsets, point_index=obs.point_index, label=huge)
        np.testing.assert_allclose(
            edge_affinity(labels, pairs, big, AffinityConfig()),
            edge_affinity(labels, pairs, obs, AffinityConfig()),
            atol=1e-7,
        )

    def test_coarsen_equals_rebuild(self) -> None:
        labels, _, obs = _random_case(6)
        merge = np.random.default_rng(6).integers(0, 8, 30)
        merged_labels = merge[labels]
        pairs = np.array([(i, j) for i in range(8) for j in range(i + 1, 8)])
        cfg = AffinityConfig()
        coarse = MaskHistograms.build(labels, obs).coarsen(merge).affinity(pairs, cfg)
        np.testing.assert_allclose(coarse, edge_affinity(merged_labels, pairs, obs, cfg), atol=1e-7)

    def test_unlabelled_primitives_ignored(self) -> None:
        labels = np.array([0, 0, 1, 1, -1, -1])
        frame = [(0, 1), (1, 1), (2, 1), (3, 1), (4, 2), (5, 2)]
        aff = edge_affinity(labels, np.array([[0, 1]]), _observations([frame]), AffinityConfig())
        assert aff[0] == pytest.approx(1.0)

    def test_language_mode(self) -> None:
        labels = np.array([0, 0, 1, 1, 2, 2])
        features = np.array([[1, 0], [1, 0], [0.6, 0.8], [0.6, 0.8], [0, 1], [0, 1]], dtype=np.float32)
        obs = _observations([[]])
        aff = edge_affinity(
            labels,
            np.array([[0, 1], [0, 2], [1, 2]]),
            obs,
            AffinityConfig(mode="language"),
            features=features,
        )
        np.testing.assert_allclose(aff, [0.6, 0.0, 0.8], atol=1e-6)

    def test_exception(self) -> None:
        labels = np.array([0, 0, 1, 1])
        obs = _observations([[]])
        with pytest.raises(InputError, match="mode 'language' needs features"):
            edge_affinity(labels, np.array([[0, 1]]), obs, AffinityConfig(mode="language"))
        with pytest.raises(ShapeError, match=r"features must be \(4, D\), found \(3, 2\)"):
            edge_affinity(labels, np.array([[0, 1]]), obs, AffinityConfig(mode="language"), features=np.ones((3, 2)))
        with pytest.raises(InputError, match=r"pairs name segments in \[0, 5\], labels have \[0, 2\)"):
            edge_affinity(labels, np.array([[0, 5]]), obs, AffinityConfig())
        with pytest.raises(ShapeError, match=r"pairs must be \(E, 2\) integers"):
            edge_affinity(labels, np.array([0, 1, 1]), obs, AffinityConfig())
        bad = MaskObservations(
            offsets=np.array([0, 1]), point_index=np.array([9], np.int32), label=np.ones(1, np.int32)
        )
        with pytest.raises(InputError, match=r"observations name primitives outside \[0, 4\)"):
            edge_affinity(labels, np.array([[0, 1]]), bad, AffinityConfig())

    def test_empty(self) -> None:
        labels = np.array([0, 1])
        out = edge_affinity(labels, np.zeros((0, 2), np.int64), _observations([[]]), AffinityConfig())
        assert out.shape == (0,)
        assert out.dtype == np.float32
