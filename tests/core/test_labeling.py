"""Stage 8 (stages/labeling/) and the label sets (language/label_sets.py)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from panogs_core.errors import ConfigError, EncoderUnavailableError, InputError, NumericalError, ShapeError
from panogs_core.language.label_sets import (
    SPACE_TEMPERATURES,
    builtin_vocabulary,
    default_temperature,
    ensure_embeddings,
    inline_vocabulary,
    load_vocabulary_file,
    vocabulary_from_name_or_file,
)
from panogs_core.stages.labeling import (
    LabelingConfig,
    PanopticLabels,
    assign_panoptic,
    instances_to_json,
    vote_in_segments,
)
from panogs_core.types import InstanceInfo, Vocabulary

WALL, FLOOR, CHAIR, TABLE = 0, 1, 2, 3


@dataclass(frozen=True)
class _Labels:
    """Stand-in for SuperPrimitives / Clusters (only ``labels`` is read)."""

    labels: np.ndarray


def _vocab() -> Vocabulary:
    # One-hot embeddings: the cosine of a one-hot feature is 1 for its class and 0 for the others.
    return Vocabulary(
        names=("wall", "floor", "chair", "table"),
        kinds=("stuff", "stuff", "thing", "thing"),
        embeddings=np.eye(4, dtype=np.float32),
    )


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(points, features, true class, cluster) of a hand-made scene; segments = 5 primitives each."""
    blocks = [  # (class, cluster, count)
        (CHAIR, 0, 60),
        (WALL, 0, 5),  # chair cluster with a few wall points
        (CHAIR, 1, 40),
        (TABLE, 1, 30),  # mixed thing cluster: majority chair
        (TABLE, 2, 10),  # too small a thing instance (min_instance_points = 20)
        (CHAIR, -1, 8),
        (FLOOR, -1, 7),  # removed cluster
        (WALL, 3, 100),
        (FLOOR, 4, 50),
    ]
    cls = np.concatenate([np.full(n, c) for c, _, n in blocks]).astype(np.int64)
    cluster = np.concatenate([np.full(n, k) for _, k, n in blocks]).astype(np.int64)
    points = np.stack([np.arange(len(cls)), cluster, np.zeros(len(cls))], 1).astype(np.float32)
    return points, np.eye(4, dtype=np.float32)[cls], cls, cluster


def _run(cfg: LabelingConfig, features: np.ndarray | None = None) -> tuple[PanopticLabels, np.ndarray]:
    points, feats, cls, cluster = _scene()
    segments = np.arange(len(cls)) // 5
    feats = feats if features is None else features
    out = assign_panoptic(points, feats, _Labels(segments), _Labels(cluster), _vocab(), cfg)
    return out, cls


class TestLabelingConfig:
    def test_smoke(self) -> None:
        cfg = LabelingConfig()
        assert cfg.vote == "islands"  # the vote restricted to small islands (see LabelingConfig)
        assert cfg.instances == "hybrid"
        assert cfg.unseen == "segment-field"
        assert cfg.unseen_field_ratio >= 1.0
        assert 0.0 <= cfg.vote_min_fraction <= 1.0

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"vote": "cluster"}, "labeling.vote"),
            ({"vote_min_fraction": 1.5}, "vote_min_fraction"),
            ({"min_instance_points": 0}, "min_instance_points"),
            ({"score_temperature": 0.0}, "score_temperature"),
            ({"split_neighbors": 0}, "split_neighbors"),
            ({"unseen_field_ratio": 0.5}, "unseen_field_ratio"),
        ],
    )
    def test_exception(self, kwargs: dict[str, object], match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            LabelingConfig(**kwargs)  # type: ignore[arg-type]


class TestVoteInSegments:
    def test_smoke(self) -> None:
        out = vote_in_segments(np.array([1, 1, 2, 3, -1]), np.array([0, 0, 0, 1, 1]))
        assert out.tolist() == [1, 1, 1, 3, 3]  # void points receive the vote

    def test_ties_go_to_smallest_class(self) -> None:
        assert vote_in_segments(np.array([4, 2, 4, 2]), np.array([0, 0, 0, 0])).tolist() == [2, 2, 2, 2]

    def test_purity_guard(self) -> None:
        classes = np.array([1, 1, 2, 3, 5, 5, 5, 6])
        segments = np.array([0, 0, 0, 0, 1, 1, 1, 1])
        # segment 0: majority 1 holds 2/4 = 0.5; segment 1: majority 5 holds 3/4.
        assert vote_in_segments(classes, segments, 0.6).tolist() == [1, 1, 2, 3, 5, 5, 5, 5]
        assert vote_in_segments(classes, segments, 0.5).tolist() == [1, 1, 1, 1, 5, 5, 5, 5]

    def test_all_void(self) -> None:
        assert vote_in_segments(np.array([-1, -1]), np.array([0, 0])).tolist() == [-1, -1]


class TestAssignPanoptic:
    # The cluster-based assembly these tests were written for (the reference's instances); the class-component
    # assembly of docs/method.md §7.5 is tested in TestComponentInstances.
    # Point counts as given: these cases test the rules, not the rescaling to the point spacing.
    cfg = LabelingConfig(
        vote="none", min_instance_points=20, score_temperature=0.5, instances="clusters", reference_spacing=None
    )

    def test_cardinality(self) -> None:
        out, cls = _run(self.cfg)
        assert out.semantic.shape == out.instance.shape == cls.shape
        assert out.semantic.dtype == out.instance.dtype == np.int64
        assert [i.id for i in out.instances] == list(range(len(out.instances)))
        assert set(np.unique(out.instance)) == {-1, *range(len(out.instances))}

    def test_feature_majority_relabel(self) -> None:
        out, cls = _run(dataclasses.replace(self.cfg, split_classes=False))
        _, _, _, cluster = _scene()
        summary = [(i.class_name, i.kind, i.num_points) for i in out.instances]
        # things by cluster id (0, 1), then stuff by class index (wall, floor); cluster 2 (10 < 20) dissolved.
        assert summary == [
            ("chair", "thing", 60),
            ("chair", "thing", 70),
            ("wall", "stuff", 105),
            ("floor", "stuff", 57),
        ]
        mixed = cluster == 1
        assert np.all(out.semantic[mixed] == CHAIR)  # panoptic consistency: the 30 table points become chair
        assert np.all(out.instance[mixed] == 1)
        small = cluster == 2
        assert np.all(out.semantic[small] == TABLE)
        assert np.all(out.instance[small] == -1)
        removed_chair = (cluster == -1) & (cls == CHAIR)
        assert np.all(out.semantic[removed_chair] == CHAIR)
        assert np.all(out.instance[removed_chair] == -1)
        assert np.all(out.instance[cls == FLOOR] == 3)  # stuff joins its class segment, even in cluster -1

    def test_feature_split_classes(self) -> None:
        out, cls = _run(self.cfg)  # split_classes is the default
        _, _, _, cluster = _scene()
        summary = [(i.class_name, i.kind, i.num_points) for i in out.instances]
        # cluster 1 (40 chair + 30 table, both >= 20) gives two instances; the 10-point table of cluster 2
        # is a fragment touching cluster 1's table in the kNN graph, so it joins it (30 + 10).
        assert summary == [
            ("chair", "thing", 60),
            ("chair", "thing", 40),
            ("table", "thing", 40),
            ("wall", "stuff", 105),
            ("floor", "stuff", 57),
        ]
        assert np.array_equal(out.semantic[cluster >= 0], cls[cluster >= 0])  # nothing relabelled
        assert np.all(out.instance[(cluster == 1) & (cls == TABLE)] == 2)
        assert np.all(out.instance[cluster == 2] == 2)
        assert np.all(out.instance[(cluster == -1) & (cls == CHAIR)] == -1)

    def test_split_noise_joins_cluster_instance(self) -> None:
        # A 2-primitive table fragment inside a 60-primitive chair cluster, touching no table instance: it
        # is class noise of that object, so it joins the chair instance and is relabelled chair.
        cls = np.array([CHAIR] * 30 + [TABLE] * 2 + [CHAIR] * 30 + [WALL] * 30)
        cluster = np.array([0] * 62 + [1] * 30)
        points = np.stack([np.arange(92), np.zeros(92), np.zeros(92)], 1).astype(np.float32)
        feats = np.eye(4, dtype=np.float32)[cls]
        out = assign_panoptic(points, feats, _Labels(np.arange(92) // 5), _Labels(cluster), _vocab(), self.cfg)
        assert [(i.class_name, i.num_points) for i in out.instances] == [("chair", 62), ("wall", 30)]
        assert np.all(out.semantic[:62] == CHAIR)

    def test_instance_info_values(self) -> None:
        out, _ = _run(dataclasses.replace(self.cfg, split_classes=False))  # instance 1: 40 chair + 30 table
        points, _, _, cluster = _scene()
        first = out.instances[0]
        member = (cluster == 0) & (np.arange(len(cluster)) < 60)
        np.testing.assert_allclose(first.centroid, points[member].mean(0), rtol=1e-6)
        np.testing.assert_allclose(first.bbox_min, points[member].min(0))
        np.testing.assert_allclose(first.bbox_max, points[member].max(0))
        np.testing.assert_allclose(first.feature, [0, 0, 1, 0], atol=1e-6)
        # Score by hand, T = 0.5: a chair point has logits (0, 0, 2, 0)
        # -> p(chair) = e^2 / (e^2 + 3) = 0.7112; a table point has logits (0, 0, 0, 2)
        # -> p(chair) = 1 / (e^2 + 3) = 0.0963.
        p_own, p_other = np.e**2 / (np.e**2 + 3), 1 / (np.e**2 + 3)
        assert first.score == pytest.approx(p_own)
        assert out.instances[1].score == pytest.approx((40 * p_own + 30 * p_other) / 70)
        mixed_feature = np.array([0, 0, 40, 30]) / 50.0  # mean of 40 chair + 30 table one-hots, normalised
        np.testing.assert_allclose(out.instances[1].feature, mixed_feature, atol=1e-6)

    def test_zero_feature_is_void(self) -> None:
        _, feats, _, _ = _scene()
        feats = feats.copy()
        feats[0] = 0.0
        out, _ = _run(self.cfg, feats)
        assert out.semantic[0] == -1
        assert out.instance[0] == -1

    def test_vote_within_superprimitives(self) -> None:
        _, feats, cls, cluster = _scene()
        feats = feats.copy()
        wall_start = int(np.flatnonzero((cls == WALL) & (cluster == 3))[0])  # a 5-point segment starts here
        feats[wall_start + 1] = np.eye(4)[FLOOR]  # one wrong point: the segment is 4/5 wall
        for fraction, expected in ((0.5, WALL), (0.9, FLOOR)):
            cfg = LabelingConfig(vote="superprimitive", vote_min_fraction=fraction, min_instance_points=20)
            out, _ = _run(cfg, feats)
            assert out.semantic[wall_start + 1] == expected
        none, _ = _run(LabelingConfig(vote="none", min_instance_points=20), feats)
        assert none.semantic[wall_start + 1] == FLOOR

    def test_exception(self) -> None:
        points, feats, _, cluster = _scene()
        seg = _Labels(np.zeros(len(points), np.int64))
        with pytest.raises(ShapeError, match="features"):
            assign_panoptic(points, feats[:, :3], seg, _Labels(cluster), _vocab(), self.cfg)
        with pytest.raises(ShapeError, match=r"clusters\.labels"):
            assign_panoptic(points, feats, seg, _Labels(cluster[:-1]), _vocab(), self.cfg)
        with pytest.raises(InputError, match="no embeddings"):
            assign_panoptic(points, feats, seg, _Labels(cluster), Vocabulary(("a",), ("thing",)), self.cfg)
        bad = feats.copy()
        bad[3, 0] = np.nan
        with pytest.raises(NumericalError, match="NaN"):
            assign_panoptic(points, bad, seg, _Labels(cluster), _vocab(), self.cfg)

    def test_save_load_round_trip(self, tmp_path: Path) -> None:
        out, _ = _run(self.cfg)
        path = tmp_path / "labels.npz"
        out.save(path)
        again = PanopticLabels.load(path)
        np.testing.assert_array_equal(again.semantic, out.semantic)
        np.testing.assert_array_equal(again.instance, out.instance)
        assert [i.to_json(with_feature=True) for i in again.instances] == [
            i.to_json(with_feature=True) for i in out.instances
        ]

    def test_save_load_empty(self, tmp_path: Path) -> None:
        void = np.full(3, -1, np.int64)
        empty = PanopticLabels(semantic=void, instance=void, instances=())
        empty.save(tmp_path / "e.npz")
        assert PanopticLabels.load(tmp_path / "e.npz").instances == ()

    def test_instances_to_json(self) -> None:
        out, _ = _run(self.cfg)
        doc = instances_to_json(out, _vocab())
        json.dumps(doc)  # plain types only
        assert doc[0]["class_name"] == "chair"
        assert len(doc[0]["centroid"]) == 3
        assert "feature" not in doc[0]
        other = Vocabulary(names=("a", "b", "c", "d"), kinds=("stuff",) * 4)
        with pytest.raises(InputError, match="not class"):
            instances_to_json(out, other)

    def test_instance_info_json_types(self) -> None:
        info = InstanceInfo(
            id=0,
            class_index=1,
            class_name="x",
            kind="thing",
            score=np.float32(0.5),
            num_points=np.int64(3),
            centroid=np.zeros(3),
            bbox_min=np.zeros(3),
            bbox_max=np.ones(3),
            feature=np.ones(2) / np.sqrt(2),
        )
        doc = info.to_json(with_feature=True)
        assert type(doc["score"]) is float
        assert type(doc["num_points"]) is int
        assert len(doc["feature"]) == 2


class _FakeEncoder:
    """A deterministic stand-in text encoder: hashes the text into a unit vector."""

    def __init__(self, space: str, dim: int) -> None:
        self.space, self.dim = space, dim
        self.seen: list[str] = []

    def encode(self, texts: list[str]) -> np.ndarray:
        self.seen.extend(texts)
        rows = [np.random.default_rng(sum(map(ord, t))).normal(size=self.dim) for t in texts]
        out = np.asarray(rows, np.float32)
        return out / np.linalg.norm(out, axis=1, keepdims=True)


class TestLabelSets:
    def test_builtin_scannet20(self) -> None:
        v = builtin_vocabulary("scannet20")
        assert len(v.names) == 20
        assert v.names[:5] == ("wall", "floor", "cabinet", "bed", "chair")
        assert v.names[-1] == "otherfurniture"
        assert [n for n, k in zip(v.names, v.kinds) if k == "stuff"] == ["wall", "floor"]
        assert v.embeddings is not None
        assert v.embeddings.shape == (20, 512)
        assert v.embeddings.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(v.embeddings, axis=1), 1.0, atol=1e-6)

    def test_builtin_matterport21(self) -> None:
        v = builtin_vocabulary("Matterport21")
        s = builtin_vocabulary("scannet20")
        assert v.names[19:] == ("other", "ceiling")
        assert v.kinds[20] == "stuff"
        assert v.embeddings is not None
        assert s.embeddings is not None
        cos = np.sum(v.embeddings[:19] * s.embeddings[:19], axis=1)
        assert cos.min() > 0.999  # rows 0-18 are the same classes (README)

    def test_builtin_other_space_drops_embeddings(self) -> None:
        assert builtin_vocabulary("scannet20", feature_space="minilm-l6").embeddings is None
        assert builtin_vocabulary("scannet20", feature_space="clip-vit-b32").embeddings is not None

    def test_builtin_exception(self) -> None:
        with pytest.raises(InputError, match="unknown built-in"):
            builtin_vocabulary("coco")

    def test_load_vocabulary_file(self, tmp_path: Path) -> None:
        np.save(tmp_path / "emb.npy", np.array([[2.0, 0.0], [0.0, 3.0]], np.float16))
        doc = {"classes": [{"name": "wall", "kind": "stuff"}, {"name": "lamp"}], "embeddings": "emb.npy"}
        (tmp_path / "vocabulary.json").write_text(json.dumps(doc))
        v = load_vocabulary_file(tmp_path / "vocabulary.json")
        assert v.names == ("wall", "lamp")
        assert v.kinds == ("stuff", "thing")
        assert v.embeddings is not None
        np.testing.assert_allclose(v.embeddings, np.eye(2))
        assert vocabulary_from_name_or_file(str(tmp_path / "vocabulary.json")).names == v.names
        assert vocabulary_from_name_or_file("SCANNET20").names[0] == "wall"

    @pytest.mark.parametrize(
        ("doc", "match"),
        [
            ({"classes": []}, "at least|>= 1 class"),
            ({"classes": [{"name": "a", "kind": "blob"}]}, "kind must be"),
            ({"classes": [{"name": "a"}, {"name": "A"}]}, "duplicate"),
            ({"classes": [{"kind": "thing"}]}, "non-empty string 'name'"),
            ({"classes": [{"name": "a"}], "embeddings": "../x.npy"}, "relative path inside"),
            ({"classes": [{"name": "a"}], "embeddings": "missing.npy"}, "cannot read embeddings"),
            ({"classes": [{"name": "a"}], "embeddings": "two.npy"}, r"float \(1, D\)"),
        ],
    )
    def test_load_exception(self, tmp_path: Path, doc: dict[str, object], match: str) -> None:
        np.save(tmp_path / "two.npy", np.ones((2, 4), np.float32))
        (tmp_path / "v.json").write_text(json.dumps(doc))
        with pytest.raises(InputError, match=match):
            load_vocabulary_file(tmp_path / "v.json")

    def test_resolve_exception(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match="no such file"):
            vocabulary_from_name_or_file(str(tmp_path / "nope.json"))
        (tmp_path / "bad.json").write_text("{not json")
        with pytest.raises(InputError, match=r"bad\.json: not valid JSON"):
            vocabulary_from_name_or_file(str(tmp_path / "bad.json"))

    def test_builtin_name_never_opens_a_path(self, tmp_path: Path) -> None:
        # A vocabulary.json that exists: the name-only resolver (the service's) refuses it without repeating it.
        doc = {"classes": [{"name": "secret-class"}]}
        (tmp_path / "vocabulary.json").write_text(json.dumps(doc))
        for spec in (str(tmp_path / "vocabulary.json"), "/etc/passwd", "../../vocabulary.json"):
            with pytest.raises(InputError, match="unknown built-in label set") as caught:
                builtin_vocabulary(spec)
            assert spec not in str(caught.value)
            assert "passwd" not in str(caught.value)
            assert str(tmp_path) not in str(caught.value)
        with pytest.raises(InputError, match="'coco'"):  # a plain name is echoed, to say what was asked
            builtin_vocabulary("coco")

    def test_inline_vocabulary(self) -> None:
        v = inline_vocabulary([{"name": " lamp "}, {"name": "rug", "kind": "stuff"}], [[3, 4], [0, 2]], source="job")
        assert v.names == ("lamp", "rug")
        assert v.kinds == ("thing", "stuff")
        assert v.embeddings is not None
        assert v.embeddings.dtype == np.float32
        np.testing.assert_allclose(v.embeddings, [[0.6, 0.8], [0.0, 1.0]], atol=1e-6)
        assert inline_vocabulary([{"name": "wall"}], None, source="job").kinds == ("stuff",)

    @pytest.mark.parametrize(
        ("classes", "embeddings", "match"),
        [
            ([], None, "at least one class"),
            ([{"name": "a"}, {"name": "A"}], None, "duplicate"),
            ([{"name": "a", "kind": "blob"}], None, "kind must be"),
            ([{"name": "a"}, {"name": "b"}], [[1.0, 0.0]], r"one row per class"),
            ([{"name": "a"}], [[0.0, 0.0]], "non-zero rows"),
            ([{"name": "a"}], [[float("nan"), 1.0]], "finite"),
        ],
    )
    def test_inline_exception(self, classes: list[dict[str, str]], embeddings: object, match: str) -> None:
        with pytest.raises(InputError, match=match):
            inline_vocabulary(classes, embeddings, source="job x vocabulary")  # type: ignore[arg-type]

    def test_ensure_embeddings(self) -> None:
        enc = _FakeEncoder("clip-vit-b32", 8)
        bare = Vocabulary(("chair", "wall"), ("thing", "stuff"))
        v = ensure_embeddings(bare, "clip-vit-b32", 8, encoder=enc)
        assert v.embeddings is not None
        assert v.embeddings.shape == (2, 8)
        assert enc.seen == ["a chair in a scene", "a wall in a scene"]  # the space's prompt template
        same = ensure_embeddings(v, "clip-vit-b32", 8)  # present and right: kept, no encoder needed
        np.testing.assert_allclose(same.embeddings, v.embeddings)  # type: ignore[arg-type]

    def test_ensure_embeddings_exception(self) -> None:
        with pytest.raises(InputError, match="features are 384-d"):
            ensure_embeddings(builtin_vocabulary("scannet20"), "minilm-l6", 384)
        bare = Vocabulary(("chair",), ("thing",))
        with pytest.raises(InputError, match="gives 8-d"):
            ensure_embeddings(bare, "clip-vit-b32", 512, encoder=_FakeEncoder("clip-vit-b32", 8))
        with pytest.raises(EncoderUnavailableError, match="'my-space'"):
            ensure_embeddings(bare, "my-space", 16)

    def test_default_temperature(self) -> None:
        v = builtin_vocabulary("matterport21")
        assert default_temperature("clip-vit-b32", None) == SPACE_TEMPERATURES["clip-vit-b32"] == 0.01
        # The spread rule lands near the measured CLIP value: 0.06 * (1 - 0.828).
        assert default_temperature(None, v.embeddings) == pytest.approx(0.0103, abs=5e-4)
        assert default_temperature("other-space", np.eye(3)) == pytest.approx(0.06)


class TestLabellingRules:
    """The labelling rules of docs/method.md §7.5: fused evidence, island vote, unseen fill, class components."""

    def test_fused_evidence_beats_a_smoothed_field(self) -> None:
        from panogs_core.stages.labeling import FusedEvidence, primitive_classes

        emb = np.eye(4, dtype=np.float32)
        field_sims = np.eye(4, dtype=np.float32)[[WALL, WALL, WALL]]  # the field smoothed all into wall
        fused = np.eye(4, dtype=np.float32)[[WALL, CHAIR, TABLE]] * 0.5
        fused[2] = 0.0  # never seen
        evidence = FusedEvidence.of(fused, emb)
        np.testing.assert_allclose(evidence.cosines[:2].max(axis=1), 1.0, rtol=1e-6)  # cosines, not dot products
        assert evidence.seen.tolist() == [True, True, False]
        cfg = LabelingConfig(evidence_fused_weight=1.0)
        assert primitive_classes(field_sims, evidence, cfg)[0].tolist() == [WALL, CHAIR, -1]
        cfg = LabelingConfig(evidence_fused_weight=0.0)
        assert primitive_classes(field_sims, evidence, cfg)[0].tolist() == [WALL, WALL, -1]

    def test_island_vote_keeps_large_patches(self) -> None:
        from panogs_core.stages.labeling import vote_islands

        # A line of 30 primitives in one segment: 20 cabinet, then a patch of 8 counter, then 2 chair.
        cls = np.array([2] * 20 + [3] * 8 + [1] * 2)
        nbr = np.stack([np.r_[1:30, 28], np.r_[1, 0:29]], 1)  # each primitive's two line neighbours
        seg = np.zeros(30, np.int64)
        out = vote_islands(cls, seg, nbr, island_points=5)
        assert out[20:28].tolist() == [3] * 8  # the 8-primitive patch survives
        assert out[28:].tolist() == [2, 2]  # the 2-primitive island joins the majority
        assert vote_islands(cls, seg, nbr, island_points=10)[20:28].tolist() == [2] * 8

    def test_island_vote_spares_confident_islands(self) -> None:
        from panogs_core.stages.labeling import vote_islands

        cls = np.array([2] * 20 + [3] * 4 + [1] * 4)
        nbr = np.stack([np.r_[1:28, 26], np.r_[1, 0:27]], 1)
        scores = np.zeros((28, 4), np.float32)
        scores[np.arange(28), cls] = 0.30
        scores[20:24, 2] = 0.299  # the counter patch: cabinet is a close second
        scores[24:, 2] = 0.10  # the chair patch: cabinet is far behind
        out = vote_islands(cls, np.zeros(28, np.int64), nbr, 10, 0.5, scores, max_margin=0.01)
        assert out[20:24].tolist() == [2] * 4  # flipped to the segment's class
        assert out[24:].tolist() == [1] * 4  # kept: its own evidence is confident

    def test_unseen_propagates_along_the_surface(self) -> None:
        from panogs_core.point_graphs import fill_nearest_seen
        from panogs_core.stages.labeling import label_unseen
        from panogs_core.stages.neighbors import build_knn

        # A floor line (2 cm spacing), seen only at both ends, under a bed top 10 cm above its middle.
        xs = np.arange(0, 1.6, 0.02)
        floor = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1)
        bed = floor[(xs > 0.5) & (xs < 1.1)] + [0, 0, 0.10]
        points = np.concatenate([floor, bed]).astype(np.float32)
        seen_floor = (xs < 0.4) | (xs > 1.2)
        cls = np.r_[np.where(seen_floor, FLOOR, -1), np.full(len(bed), TABLE)].astype(np.int64)
        nbr = build_knn(points, 4).neighbors
        sims = np.zeros((len(points), 4), np.float32)
        out, counts = label_unseen(cls, sims, points, nbr, np.arange(len(points)), "propagate")
        assert counts["unseen"] == counts["graph"] == int((cls < 0).sum())
        assert (out[: len(xs)] == FLOOR).all()  # along the floor, not up to the bed 10 cm above
        assert (fill_nearest_seen(points, cls)[: len(xs)] == TABLE).any()  # what Euclidean fill would do
        segs = np.r_[np.zeros(len(xs)), np.ones(len(bed))].astype(np.int64)
        assert (label_unseen(cls, sims, points, nbr, segs, "segment")[0][: len(xs)] == FLOOR).all()
        assert (label_unseen(cls, np.eye(4, dtype=np.float32)[np.full(len(points), WALL)], points, nbr, segs,
                             "field")[0] != FLOOR).any()  # fmt: skip

    def test_field_checked_unseen_rule_keeps_a_thin_object_out_of_its_wall(self) -> None:
        from panogs_core.stages.labeling import label_unseen
        from panogs_core.stages.neighbors import build_knn

        # A wall (plane x = 0, 4 cm grid) with a thin object (class TABLE standing in for a window) set into it at
        # the top: the wall's lower half and the object's lowest rows are seen, the rest of both is not, and the
        # graph cut put the object into the wall's segment. The field says the object where it is.
        ys, zs = np.meshgrid(np.arange(0, 2.0, 0.04), np.arange(0, 2.0, 0.04))
        wall = np.stack([np.zeros(ys.size), ys.ravel(), zs.ravel()], 1).astype(np.float32)
        thin = (wall[:, 1] > 0.6) & (wall[:, 1] < 1.4) & (wall[:, 2] > 1.5)
        seen = (wall[:, 2] < 1.0) | (thin & (wall[:, 2] < 1.6))
        cls = np.where(seen, np.where(thin, TABLE, WALL), -1).astype(np.int64)
        sims = 0.2 * np.eye(4, dtype=np.float32)[np.where(thin, TABLE, WALL)]
        nbr = build_knn(wall, 6).neighbors
        segs = np.zeros(len(wall), np.int64)  # one segment: the wall's
        plain, _ = label_unseen(cls, sims, wall, nbr, segs, "segment")
        checked, counts = label_unseen(cls, sims, wall, nbr, segs, "segment-field", 0.04)
        assert (plain[thin & ~seen] == WALL).all()  # the segment rule hands the object the wall's class
        assert (checked[thin & ~seen] == TABLE).mean() > 0.8
        assert (checked[~thin & ~seen] == WALL).all()  # the wall's nearest seen primitive is wall, or the field
        assert counts["field"] == int(((checked != plain) & ~seen).sum()) > 0
        assert sum(counts[k] for k in ("segment", "graph", "nearest", "field")) == counts["unseen"]
        # The other way round (a door's segment holding unseen wall beside it): the same rule, classes swapped.
        swap = np.array([TABLE, FLOOR, CHAIR, WALL])
        out, _ = label_unseen(np.where(cls >= 0, swap[np.maximum(cls, 0)], -1), sims[:, swap], wall, nbr, segs,
                              "segment-field", 0.04)  # fmt: skip
        assert (out[~thin & ~seen] == TABLE).all()
        assert (out[thin & ~seen] == WALL).mean() > 0.8
        # A field that leads by less than the margin, or whose argmax is a third class, leaves the segment's class.
        assert (label_unseen(cls, sims, wall, nbr, segs, "segment-field", 0.5)[0] == plain).all()
        third = sims.copy()
        third[:, CHAIR] = 0.3
        assert (label_unseen(cls, third, wall, nbr, segs, "segment-field", 0.04)[0] == plain).all()

    def test_the_unseen_rules_first_search_may_come_made_for_the_same_unseen_primitives(self) -> None:
        """The pipeline makes ``segment-field``'s first graph search beside the field's fit: made for the same
        unseen primitives, it is the one used (the same labels as searching here); made for others, it is not."""
        from panogs_core.stages.labeling import NearestSeen, label_unseen, nearest_seen
        from panogs_core.stages.neighbors import build_knn

        ys, zs = np.meshgrid(np.arange(0, 2.0, 0.04), np.arange(0, 2.0, 0.04))
        wall = np.stack([np.zeros(ys.size), ys.ravel(), zs.ravel()], 1)  # float64: converted as the labelling does
        thin = (wall[:, 1] > 0.6) & (wall[:, 1] < 1.4) & (wall[:, 2] > 1.5)
        seen = (wall[:, 2] < 1.0) | (thin & (wall[:, 2] < 1.6))
        cls = np.where(seen, np.where(thin, TABLE, WALL), -1).astype(np.int64)
        sims = 0.2 * np.eye(4, dtype=np.float32)[np.where(thin, TABLE, WALL)]
        nbr = build_knn(wall.astype(np.float32), 6).neighbors
        segs = np.zeros(len(wall), np.int64)
        pts = wall.astype(np.float32)
        searched, counts = label_unseen(cls, sims, pts, nbr, segs, "segment-field", 0.04)
        made = nearest_seen(wall, nbr, cls < 0)
        given, given_counts = label_unseen(cls, sims, pts, nbr, segs, "segment-field", 0.04, made)
        assert np.array_equal(given, searched)
        assert given_counts == counts
        assert counts["field"] > 0
        # A search that says every unseen primitive's nearest seen one is a wall primitive: used, it changes labels.
        a_wall_point = int(np.flatnonzero(seen & ~thin)[0])
        wrong = NearestSeen(made.unseen, np.where(made.source >= 0, a_wall_point, -1))
        assert not np.array_equal(label_unseen(cls, sims, pts, nbr, segs, "segment-field", 0.04, wrong)[0], searched)
        other = NearestSeen(~made.unseen, wrong.source)  # made for other unseen primitives: searched here instead
        assert np.array_equal(label_unseen(cls, sims, pts, nbr, segs, "segment-field", 0.04, other)[0], searched)

    def test_field_checked_unseen_rule_keeps_the_floor_under_a_table(self) -> None:
        from panogs_core.stages.labeling import label_unseen
        from panogs_core.stages.neighbors import build_knn

        # The floor under a table (plane z = 0) beside a seen leg: its nearest seen primitive is the leg's, but the
        # field there says floor, as it does under real tables, so the segment's class stays.
        xs, ys = np.meshgrid(np.arange(0, 1.0, 0.04), np.arange(0, 1.0, 0.04))
        floor = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
        leg = np.stack([np.full(20, 0.5), np.full(20, 0.5), np.arange(1, 21) * 0.04], 1)
        points = np.concatenate([floor, leg]).astype(np.float32)
        under = np.r_[np.hypot(floor[:, 0] - 0.5, floor[:, 1] - 0.5) < 0.3, np.zeros(20, bool)]
        cls = np.r_[np.where(under[: len(floor)], -1, FLOOR), np.full(20, TABLE)].astype(np.int64)
        sims = 0.2 * np.eye(4, dtype=np.float32)[np.r_[np.full(len(floor), FLOOR), np.full(20, TABLE)]]
        segs = np.r_[np.zeros(len(floor)), np.ones(20)].astype(np.int64)
        nbr = build_knn(points, 6).neighbors
        out, counts = label_unseen(cls, sims, points, nbr, segs, "segment-field", 0.04)
        assert (out[under] == FLOOR).all()
        assert counts["field"] == 0
        assert (label_unseen(cls, sims, points, nbr, segs, "propagate")[0][under] == TABLE).any()

    def test_components_split_only_by_large_clusters(self) -> None:
        # Three touching chairs in a row (one class component), each its own cluster, and a fourth cluster
        # that is a small part (a leg) of the first chair.
        from panogs_core.stages.neighbors import build_knn

        xs = np.arange(0, 1.5, 0.01)
        points = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1).astype(np.float32)
        cluster = (xs // 0.5).astype(np.int64)
        cluster[:10] = 3  # the leg
        cls = np.full(len(xs), CHAIR, np.int64)
        nbr = build_knn(points, 4).neighbors
        sims = np.eye(4, dtype=np.float32)[cls]
        cfg = LabelingConfig(
            vote="none", min_instance_points=20, split_min_points=30, split_min_fraction=0.2, reference_spacing=None
        )
        out = assign_panoptic(points, sims, _Labels(np.zeros(len(xs), np.int64)), _Labels(cluster), _vocab(), cfg,
                              neighbors=nbr)  # fmt: skip
        assert len(np.unique(out.instance)) == 3
        assert len(np.unique(out.instance[:50])) == 1  # the leg stays with its chair
        merged = assign_panoptic(points, sims, _Labels(np.zeros(len(xs), np.int64)), _Labels(cluster), _vocab(),
                                 dataclasses.replace(cfg, instances="components"), neighbors=nbr)  # fmt: skip
        assert len(np.unique(merged.instance)) == 1

    def test_an_unseen_cluster_never_splits_a_component(self) -> None:
        # A bathtub line of 150 primitives, one class: the first 100 seen, in one cluster; the last 50 seen by no
        # key frame, clustered apart for want of masks. They are no second tub.
        from panogs_core.stages.neighbors import build_knn

        xs = np.arange(0, 1.5, 0.01)
        points = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1).astype(np.float32)
        cluster = (xs >= 1.0).astype(np.int64)
        sims = np.eye(4, dtype=np.float32)[np.full(len(xs), CHAIR)]
        fused = sims.copy()
        fused[100:] = 0.0
        cfg = LabelingConfig(vote="none", min_instance_points=20, split_min_points=30, reference_spacing=None)
        args = (points, sims, _Labels(np.zeros(len(xs), np.int64)), _Labels(cluster), _vocab(), cfg)
        nbr = build_knn(points, 4).neighbors
        assert len(np.unique(assign_panoptic(*args, neighbors=nbr).instance)) == 2  # both clusters seen: split
        out = assign_panoptic(*args, neighbors=nbr, fused=fused)
        assert len(np.unique(out.instance)) == 1
        assert (out.semantic == CHAIR).all()
        # The pipeline passes the fused features' evidence instead of the (N, D) features: the same labels.
        from panogs_core.stages.labeling import FusedEvidence, unit_embeddings

        evidence = FusedEvidence.of(fused, unit_embeddings(_vocab()))
        by_evidence = assign_panoptic(*args, neighbors=nbr, fused=evidence)
        np.testing.assert_array_equal(by_evidence.semantic, out.semantic)
        np.testing.assert_array_equal(by_evidence.instance, out.instance)
        with pytest.raises(ShapeError, match="fused"):
            assign_panoptic(*args, neighbors=nbr, fused=FusedEvidence.of(fused[:-1], unit_embeddings(_vocab())))

    def test_every_primitive_gets_a_class(self) -> None:
        points, feats, cls, cluster = _scene()
        fused = feats.copy()
        fused[::3] = 0.0  # a third never seen
        out = assign_panoptic(points, feats, _Labels(np.arange(len(cls)) // 5), _Labels(cluster), _vocab(),
                              LabelingConfig(min_instance_points=20), fused=fused)  # fmt: skip
        assert (out.semantic >= 0).all()
        assert (out.semantic == cls).mean() > 0.9
        assert out.unseen["unseen"] == len(cls[::3])
        assert sum(out.unseen[k] for k in ("segment", "graph", "nearest", "field")) == out.unseen["unseen"]

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"unseen": "nearest"}, "labeling.unseen"),
            ({"instances": "sam"}, "labeling.instances"),
            ({"evidence_fused_weight": 2.0}, "evidence_fused_weight"),
            ({"component_radius": 0.0}, "component_radius"),
            ({"split_min_fraction": -0.1}, "split_min_fraction"),
            ({"vote_max_ratio": 2.0}, "vote_max_ratio"),
        ],
    )
    def test_exception(self, kwargs: dict[str, object], match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            LabelingConfig(**kwargs)  # type: ignore[arg-type]


class TestPointSpacing:
    """Point counts and the join radius follow the point spacing (``scaled_to_spacing``)."""

    def test_counts_scale_with_the_area_a_point_stands_for(self) -> None:
        from panogs_core.stages.labeling import scaled_to_spacing

        cfg = LabelingConfig(island_points=100, split_min_points=200, min_instance_points=40, component_radius=0.1)
        coarse = scaled_to_spacing(cfg, 2 * cfg.reference_spacing)  # a point stands for 4x the area
        assert (coarse.island_points, coarse.split_min_points, coarse.min_instance_points) == (25, 50, 10)
        assert coarse.component_radius == pytest.approx(0.2)
        dense = scaled_to_spacing(cfg, cfg.reference_spacing / 2)
        assert (dense.island_points, dense.split_min_points, dense.min_instance_points) == (400, 800, 160)
        assert dense.component_radius == pytest.approx(0.1)  # a gap in metres does not shrink
        assert scaled_to_spacing(dataclasses.replace(cfg, reference_spacing=None), 1.0) == dataclasses.replace(
            cfg, reference_spacing=None
        )

    def test_a_coarse_object_stays_one_instance(self) -> None:
        # A row of 30 chair points 6 cm apart: as given, 10 cm joins hold but 50 points are too few for an
        # instance; at the spacing they stand for (6 cm, not 3.7 cm) they make one chair.
        xs = np.arange(30, dtype=np.float32) * 0.06
        points = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
        nbr = np.stack([np.clip(np.arange(30) + d, 0, 29) for d in (1, -1)], axis=1)
        nbr[-1, 0], nbr[0, 1] = 28, 1
        feats = np.tile(np.eye(4, dtype=np.float32)[2], (30, 1))  # chair (a thing) everywhere
        labels = _Labels(np.zeros(30, np.int64))
        as_given = assign_panoptic(
            points, feats, labels, labels, _vocab(), LabelingConfig(reference_spacing=None), neighbors=nbr
        )
        scaled = assign_panoptic(points, feats, labels, labels, _vocab(), LabelingConfig(), neighbors=nbr)
        assert as_given.instance.max() == -1
        assert np.unique(scaled.instance).tolist() == [0]
