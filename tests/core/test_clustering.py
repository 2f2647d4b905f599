"""Stage 7: progressive clustering on two boxes on a floor, the BFS rule, small clusters, config errors."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.progress import ProgressFn
from panogs_core.stages.affinity import AffinityConfig, segment_affinity
from panogs_core.stages.clustering import (
    ClusteringConfig,
    Clusters,
    _grow_clusters,
    _symmetric_graph,
    progressive_clustering,
)
from panogs_core.stages.masks import MaskObservations
from panogs_core.stages.neighbors import KnnGraph
from panogs_core.stages.superprimitives import SuperPrimitives


def _cluster(
    sp: SuperPrimitives,
    knn: KnnGraph,
    obs: MaskObservations,
    cfg: ClusteringConfig,
    affinity_cfg: AffinityConfig,
    *,
    features: np.ndarray | None = None,
    on_progress: ProgressFn | None = None,
) -> Clusters:
    """The pipeline's stage 7: the affinity measure bound to the observations, then the clustering."""
    affinity = segment_affinity(sp.labels, obs, affinity_cfg, features=features)
    return progressive_clustering(sp, knn, affinity, cfg, on_progress=on_progress)


FLOOR, BOX_A, BOX_B = 0, 1, 2


def _box_surface(x0: float, y0: float, side: float, step: float) -> np.ndarray:  # (P, 3)
    """Top and four sides of an axis-aligned cube standing on z = 0."""
    ticks = np.arange(step / 2, side, step)
    u, w = (g.ravel() for g in np.meshgrid(ticks, ticks))
    top = np.stack([x0 + u, y0 + w, np.full_like(u, side)], 1)
    sides = [
        np.stack([x0 + u, np.full_like(u, y0), w], 1),
        np.stack([x0 + u, np.full_like(u, y0 + side), w], 1),
        np.stack([np.full_like(u, x0), y0 + u, w], 1),
        np.stack([np.full_like(u, x0 + side), y0 + u, w], 1),
    ]
    return np.concatenate([top, *sides])


@dataclass(frozen=True)
class _Scene:
    points: np.ndarray  # (N, 3)
    objects: np.ndarray  # (N,) int64: FLOOR, BOX_A, BOX_B
    superprimitives: np.ndarray  # (N,) int64 dense
    knn: KnnGraph


def _two_boxes_on_floor() -> _Scene:
    gx, gy = np.meshgrid(np.arange(0.02, 2.0, 0.04), np.arange(0.02, 1.0, 0.04))
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    box_a = _box_surface(0.3, 0.35, 0.3, 0.03)
    box_b = _box_surface(1.3, 0.35, 0.3, 0.03)
    points = np.concatenate([floor, box_a, box_b])
    objects = np.repeat([FLOOR, BOX_A, BOX_B], [len(floor), len(box_a), len(box_b)])
    # Super-primitives: floor quadrants (split at x = 1, y = 0.5); per box its top (split at the top's centre
    # line) and its sides. The top halves let tests carve out small pieces.
    quadrant = (points[:, 0] >= 1.0).astype(int) * 2 + (points[:, 1] >= 0.5)
    is_top = points[:, 2] > 0.29
    centre_x = np.where(objects == BOX_A, 0.45, 1.45)
    part = np.where(is_top, np.where(points[:, 0] < centre_x, 0, 1), 2)
    raw = np.where(objects == FLOOR, quadrant, 4 + (objects - 1) * 3 + part)
    sp = np.unique(raw, return_inverse=True)[1].astype(np.int64)
    distances, neighbors = cKDTree(points).query(points, k=8)
    knn = KnnGraph(neighbors=neighbors[:, 1:].astype(np.int64), distances=distances[:, 1:].astype(np.float32))
    return _Scene(points=points, objects=objects.astype(np.int64), superprimitives=sp, knn=knn)


def _observe(
    scene: _Scene,
    object_ids: np.ndarray,  # (N,) int64, which "true mask" each point belongs to
    num_frames: int = 8,
    split_floor_frames: tuple[int, ...] = (1, 5),
    seed: int = 0,
) -> MaskObservations:
    """Synthetic SAM-like masks: one id per object per frame, fresh ids every frame.

    Some points are unseen or outside every mask; in ``split_floor_frames`` the floor is over-segmented into
    its x < 1 and x >= 1 halves. ``object_ids`` -1 = never inside a mask.
    """
    rng = np.random.default_rng(seed)
    num_points = len(scene.points)
    offsets, index, label = [0], [], []
    for frame in range(num_frames):
        kinds = object_ids.copy()
        if frame in split_floor_frames:
            kinds = np.where((object_ids == FLOOR) & (scene.points[:, 0] >= 1.0), 99, kinds)
        kind_values = np.unique(kinds[kinds >= 0])
        ids = rng.permutation(len(kind_values)) + 1 + 10 * frame
        mask_id = np.zeros(num_points, dtype=np.int64)
        known = kinds >= 0
        mask_id[known] = ids[np.searchsorted(kind_values, kinds[known])]
        seen = np.flatnonzero((rng.random(num_points) < 0.8) & (rng.random(num_points) > 0.05) & known)
        index.append(seen.astype(np.int32))
        label.append(mask_id[seen].astype(np.int32))
        offsets.append(offsets[-1] + seen.size)
    return MaskObservations(
        offsets=np.array(offsets, dtype=np.int64),
        point_index=np.concatenate(index),
        label=np.concatenate(label),
    )


def _assert_matches(clusters: np.ndarray, truth: np.ndarray) -> None:
    """Each true group is exactly one cluster, and different groups are different clusters."""
    pairs = {(int(t), int(c)) for t, c in zip(truth.tolist(), clusters.tolist(), strict=True)}
    assert len(pairs) == len(np.unique(truth)), pairs
    assert len({c for _, c in pairs}) == len(pairs), pairs


@pytest.fixture(scope="module")
def scene() -> _Scene:
    return _two_boxes_on_floor()


class TestClusteringConfig:
    def test_smoke(self) -> None:
        cfg = ClusteringConfig()
        assert cfg.thresholds == (0.9, 0.8, 0.7, 0.6)
        assert cfg.two_hop_weight == 0.5
        assert (cfg.small_cluster_max_parts, cfg.small_cluster_max_points) == (2, 200)

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"thresholds": ()}, r"clustering\.thresholds: expected one or more numbers, found \(\)"),
            ({"thresholds": (0.9, float("nan"))}, r"clustering\.thresholds: expected one or more numbers"),
            ({"thresholds": (1.5,)}, r"clustering\.thresholds: expected values in \[-1, 1\], found \[1\.5\]"),
            ({"thresholds": (0.6, 0.9)}, r"expected non-increasing values, found \[0\.6, 0\.9\]"),
            (
                {"two_hop_weight": 2.0},
                r"clustering\.two_hop_weight: expected a number in \[0, 1\], found 2\.0",
            ),
            (
                {"small_cluster_max_parts": -1},
                r"clustering\.small_cluster_max_parts: expected an integer >= 0",
            ),
            ({"small_cluster_max_points": 2.5}, r"clustering\.small_cluster_max_points: expected an integer"),
            (
                {"unmerged_small": "drop"},
                r"clustering\.unmerged_small: expected 'adjacent', 'void' or 'keep'",
            ),
        ],
    )
    def test_exception(self, kwargs: dict, match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            ClusteringConfig(**kwargs)


class TestProgressiveClustering:
    def _run(self, scene: _Scene, obs: MaskObservations, aggregate: str = "mean", **kwargs: object) -> np.ndarray:
        cfg = ClusteringConfig(**kwargs)  # type: ignore[arg-type]
        sp = SuperPrimitives(labels=scene.superprimitives)
        affinity = AffinityConfig(aggregate=aggregate)  # type: ignore[arg-type]
        return _cluster(sp, scene.knn, obs, cfg, affinity).labels

    def test_two_boxes_on_floor(self, scene: _Scene) -> None:
        calls: list[tuple[int, int]] = []
        sp = SuperPrimitives(labels=scene.superprimitives)
        clusters = _cluster(
            sp,
            scene.knn,
            _observe(scene, scene.objects),
            ClusteringConfig(),
            AffinityConfig(),
            on_progress=lambda d, t: calls.append((d, t)),
        )
        assert clusters.count == 3
        _assert_matches(clusters.labels, scene.objects)
        assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]

    def test_floor_halves_join_in_a_later_round(self, scene: _Scene) -> None:
        # The over-segmented frames put the floor halves at ~0.83 (6 frames alike, 2 disjoint): one round at
        # 0.9 keeps them apart, a second at 0.8 joins them.
        obs = _observe(scene, scene.objects)
        one_round = self._run(scene, obs, thresholds=(0.9,), small_cluster_max_parts=0)
        halves = np.where(scene.objects == FLOOR, 10 + (scene.points[:, 0] >= 1.0), scene.objects)
        _assert_matches(one_round, halves)
        _assert_matches(self._run(scene, obs, thresholds=(0.9, 0.8)), scene.objects)
        # The weighted median sides with the 6 frames that see one floor: one round at 0.9 is enough.
        _assert_matches(self._run(scene, obs, "median", thresholds=(0.9,), small_cluster_max_parts=0), scene.objects)

    def test_small_cluster_merge(self, scene: _Scene) -> None:
        # A 10-point piece of box A's top is its own mask in 5 of 8 frames: affinity to box A is about
        # (3 + 5 (1 - ln 2)) / 8 = 0.57 < 0.6, so no BFS round takes it; the small-cluster rule does.
        piece = (scene.objects == BOX_A) & (scene.points[:, 2] > 0.29) & (scene.points[:, 0] < 0.33)
        piece &= scene.points[:, 1] < 0.65
        assert 5 <= piece.sum() < 200
        labels = scene.superprimitives.copy()
        labels[piece] = labels.max() + 1
        scene = _Scene(scene.points, scene.objects, labels, scene.knn)
        obs_own = _observe(scene, np.where(piece, 7, scene.objects), seed=1)
        obs_box = _observe(scene, scene.objects, seed=1)
        obs = _mix_frames(obs_own, obs_box, own_frames=(0, 2, 4, 6, 7))
        merged = self._run(scene, obs)
        _assert_matches(merged, scene.objects)
        kept = self._run(scene, obs, small_cluster_max_parts=0)
        _assert_matches(kept, np.where(piece, 7, scene.objects))

    @pytest.mark.parametrize("policy", ["adjacent", "void", "keep"])
    def test_unmergeable_small_cluster(self, scene: _Scene, policy: str) -> None:
        # A piece of box B's top that no mask ever covers has affinity 0 to everything.
        piece = (scene.objects == BOX_B) & (scene.points[:, 2] > 0.29) & (scene.points[:, 0] > 1.55)
        labels = scene.superprimitives.copy()
        labels[piece] = labels.max() + 1
        scene = _Scene(scene.points, scene.objects, labels, scene.knn)
        obs = _observe(scene, np.where(piece, -1, scene.objects))
        out = self._run(scene, obs, unmerged_small=policy)
        if policy == "adjacent":
            _assert_matches(out, scene.objects)
        elif policy == "void":
            assert np.all(out[piece] == -1)
            assert np.all(out[~piece] >= 0)
            _assert_matches(out[~piece], scene.objects[~piece])
        else:
            _assert_matches(out, np.where(piece, 7, scene.objects))

    def test_language_mode(self, scene: _Scene) -> None:
        features = np.eye(3, dtype=np.float32)[scene.objects]
        sp = SuperPrimitives(labels=scene.superprimitives)
        obs = _observe(scene, scene.objects)
        clusters = _cluster(sp, scene.knn, obs, ClusteringConfig(), AffinityConfig(mode="language"), features=features)
        _assert_matches(clusters.labels, scene.objects)

    def test_save_load(self, scene: _Scene, tmp_path: Path) -> None:
        clusters = Clusters(labels=np.array([0, 1, -1, 1], dtype=np.int64))
        clusters.save(tmp_path / "clusters.npz")
        back = Clusters.load(tmp_path / "clusters.npz")
        np.testing.assert_array_equal(back.labels, clusters.labels)
        assert back.count == 2

    def test_exception(self, scene: _Scene) -> None:
        sp = SuperPrimitives(labels=scene.superprimitives)
        obs = _observe(scene, scene.objects)
        short = KnnGraph(neighbors=scene.knn.neighbors[:-1], distances=scene.knn.distances[:-1])
        with pytest.raises(ShapeError, match=r"knn\.neighbors must be \(\d+, K\) to match labels"):
            _cluster(sp, short, obs, ClusteringConfig(), AffinityConfig())
        with pytest.raises(InputError, match="mode 'language' needs features"):
            _cluster(sp, scene.knn, obs, ClusteringConfig(), AffinityConfig(mode="language"))

    def test_sparse_ids_give_dense_clusters(self, scene: _Scene) -> None:
        sp = SuperPrimitives(labels=scene.superprimitives * 3)  # ids with no primitive in between
        out = _cluster(sp, scene.knn, _observe(scene, scene.objects), ClusteringConfig(), AffinityConfig())
        np.testing.assert_array_equal(np.unique(out.labels), [0, 1, 2])
        _assert_matches(out.labels, scene.objects)

    def test_single_segment(self) -> None:
        sp = SuperPrimitives(labels=np.zeros(5, dtype=np.int64))
        knn = KnnGraph(neighbors=np.zeros((5, 1), np.int64), distances=np.zeros((5, 1), np.float32))
        obs = MaskObservations(
            offsets=np.zeros(1, np.int64), point_index=np.zeros(0, np.int32), label=np.zeros(0, np.int32)
        )
        out = _cluster(sp, knn, obs, ClusteringConfig(), AffinityConfig())
        np.testing.assert_array_equal(out.labels, 0)


def _mix_frames(own: MaskObservations, other: MaskObservations, own_frames: tuple[int, ...]) -> MaskObservations:
    """Frame v from ``own`` when v is in ``own_frames``, else from ``other``."""
    offsets, index, label = [0], [], []
    for v in range(own.num_frames):
        src = own if v in own_frames else other
        lo, hi = src.offsets[v], src.offsets[v + 1]
        index.append(src.point_index[lo:hi])
        label.append(src.label[lo:hi])
        offsets.append(offsets[-1] + hi - lo)
    return MaskObservations(
        offsets=np.array(offsets, dtype=np.int64),
        point_index=np.concatenate(index),
        label=np.concatenate(label),
    )


class TestGrowClusters:
    """The BFS pass of docs/method.md §6.1 on hand-made graphs."""

    def _graph(self, affinity: dict[tuple[int, int], float], direct: set[tuple[int, int]], sizes: list[float]):
        pool = np.array(sorted(affinity), dtype=np.int64)
        return _symmetric_graph(
            np.array(sizes, dtype=np.float64),
            pool,
            np.array([tuple(p) in direct for p in pool.tolist()]),
            np.array([affinity[tuple(p)] for p in pool.tolist()], dtype=np.float64),
            np.zeros(len(pool)),
        )

    def test_two_hop_members_count_half(self) -> None:
        # Chain 0 - 1 - 2; 0 and 2 are 2-hop. Testing 2 from cluster {0, 1}:
        # (0.9 * 100 + 0.5 * 0.5 * 100) / (100 + 0.5 * 100) = 0.767.
        graph = self._graph({(0, 1): 1.0, (1, 2): 0.9, (0, 2): 0.5}, {(0, 1), (1, 2)}, [100, 100, 100])
        np.testing.assert_array_equal(_grow_clusters(graph, 0.8, 0.5), [0, 0, 1])
        np.testing.assert_array_equal(_grow_clusters(graph, 0.76, 0.5), [0, 0, 0])
        np.testing.assert_array_equal(_grow_clusters(graph, 0.8, 0.0), [0, 0, 0])

    def test_point_count_weighting(self) -> None:
        # Does 3 join {0, 1, 2}? Direct to 1 (90 points, alike) and 2 (10 points, unlike), 2-hop to 0 (50
        # points at half weight, affinity 0): (0.9 * 90 + 0.1 * 10 + 0 * 25) / (90 + 10 + 25) = 0.656.
        graph = self._graph(
            {(0, 1): 1.0, (0, 2): 1.0, (1, 3): 0.9, (2, 3): 0.1, (0, 3): 0.0, (1, 2): 1.0},
            {(0, 1), (0, 2), (1, 3), (2, 3), (1, 2)},
            [50, 90, 10, 20],
        )
        np.testing.assert_array_equal(_grow_clusters(graph, 0.65, 0.5), [0, 0, 0, 0])
        np.testing.assert_array_equal(_grow_clusters(graph, 0.66, 0.5), [0, 0, 0, 1])

    def test_rejected_node_is_retested(self) -> None:
        # 0 - 1 (0.5: rejected from 0), 0 - 2 (1.0), 2 - 1 (1.0): 1 is tested again from 2 and then joins,
        # because the cluster {0, 2} now scores (0.5 * 10 + 1.0 * 90) / 100 = 0.95.
        graph = self._graph({(0, 1): 0.5, (0, 2): 1.0, (1, 2): 1.0}, {(0, 1), (0, 2), (1, 2)}, [10, 10, 90])
        np.testing.assert_array_equal(_grow_clusters(graph, 0.9, 0.5), [0, 0, 0])

    def test_seeds_in_ascending_order(self) -> None:
        graph = self._graph({(0, 1): 0.1, (1, 2): 1.0}, {(0, 1), (1, 2)}, [1, 1, 1])
        np.testing.assert_array_equal(_grow_clusters(graph, 0.5, 0.5), [0, 1, 1])
