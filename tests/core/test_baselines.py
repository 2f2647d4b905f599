"""The baselines (evaluation/baselines.py, docs/method.md §7.5): fused argmax, nearest-seen fill, class components."""

from __future__ import annotations

import numpy as np

from panogs_core.evaluation.baselines import fused_argmax, label_components
from panogs_core.point_graphs import fill_nearest_seen, radius_pairs


def test_fused_argmax_marks_unseen() -> None:
    emb = np.array([[1.0, 0.0], [0.6, 0.8]])
    feats = np.array([[0.9, 0.1], [0.0, 0.5], [0.0, 0.0]])
    assert fused_argmax(feats, emb).tolist() == [0, 1, -1]


def test_fill_takes_the_nearest_seen_class() -> None:
    points = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.9, 0, 0], [1.0, 0, 0]])
    assert fill_nearest_seen(points, np.array([4, -1, -1, 7])).tolist() == [4, 4, 7, 7]
    assert fill_nearest_seen(points, np.full(4, -1)).tolist() == [-1] * 4


def test_components_respect_radius_and_size() -> None:
    # Two chairs 5 cm apart (joined at 10 cm, apart at 3 cm), a 3-point speck, and a wall.
    chair_a = np.stack([np.arange(0, 0.2, 0.02), np.zeros(10), np.zeros(10)], 1)
    chair_b = chair_a + np.array([0.25, 0.0, 0.0])
    speck = np.array([[3.0, 0, 0], [3.01, 0, 0], [3.02, 0, 0]])
    wall = np.stack([np.zeros(5), np.full(5, 2.0), np.arange(5) * 0.02], 1)
    points = np.concatenate([chair_a, chair_b, speck, wall])
    semantic = np.r_[np.ones(23), np.zeros(5)].astype(np.int64)
    is_thing = np.array([False, True])
    joined = label_components(points, semantic, is_thing, radius=0.10, min_points=5)
    assert len(np.unique(joined[:20])) == 1
    assert (joined[20:23] == -1).all()
    apart = label_components(points, semantic, is_thing, radius=0.03, min_points=5)
    assert apart[0] != apart[10]
    assert (apart[:10] == apart[0]).all()
    assert len(np.unique(apart[23:])) == 1
    assert apart[23] not in apart[:23]
    assert len(radius_pairs(points, 0.03)) > 0
