"""Open-vocabulary instance queries: a text or a vector in, ranked instances out.

Scoring (why not the raw cosine): in the CLIP space every class embedding is 0.68-0.94 similar to every
other, and instance features sit at a similar cosine from many classes, so ``cos(feature, "chair")`` barely
separates chairs from tables. Instead each instance is scored by how much the query beats the vocabulary on
that instance:

    p = softmax over [query] + [competitor classes] of cos(feature, .) / T, taken at the query

where the competitors are the vocabulary classes that are not near-synonyms of the query. A chair instance
is closer to "chair" than to "table", so "chair" wins there (p high) and loses on a table (p < 0.5, "table"
beats it). A query that names a vocabulary class (case-insensitive) uses that class's embedding and competes
with every other class, so no encoder is needed. Temperatures: ``label_sets.SPACE_TEMPERATURES`` (measured
there).

DEPARTURE (docs/method.md §7.5): for free text and vectors the near-synonym classes ("sofa" for "couch") join
the query's side of the softmax instead of being dropped.

Needs only numpy (the service answers queries without torch, unless a text must be encoded).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from panogs_core.errors import EncoderUnavailableError, InputError, ShapeError
from panogs_core.language.label_sets import default_temperature
from panogs_core.language.text_encoders import TextEncoder, encode_labels, get_text_encoder
from panogs_core.types import InstanceInfo, Vocabulary

# A class at least this similar to a free-text or vector query is a near-synonym and does not compete with it.
# CLIP: distinct label-set classes reach 0.94 (table/desk; chair/table 0.904), so 0.9 would let "chair" find
# tables; MiniLM: distinct classes reach 0.85 (curtain/shower curtain), synonyms sit at 0.82-0.96
# (chair/chairs 0.82, sofa/couch 0.86, bathtub/tub 0.88, refrigerator/fridge 0.96).
SYNONYM_COS = {"clip-vit-b32": 0.95, "minilm-l6": 0.8}
# Other spaces: 0.9, raised above the most similar pair of distinct vocabulary classes (plus 0.01), since two
# classes of one label set are never synonyms of each other (in the CLIP label sets this gives 0.948).
DEFAULT_SYNONYM_COS = 0.9


@dataclass(frozen=True)
class QueryHit:
    """One instance answering a query."""

    instance_id: int
    class_name: str
    score: float  # in [0, 1], see the module docstring
    centroid: np.ndarray  # (3,) float32
    bbox_min: np.ndarray  # (3,) float32
    bbox_max: np.ndarray  # (3,) float32

    def to_json(self) -> dict[str, Any]:
        """Plain dict (ints, floats, lists)."""
        return {
            "instance_id": int(self.instance_id),
            "class_name": self.class_name,
            "score": float(self.score),
            "centroid": [float(v) for v in self.centroid],
            "bbox_min": [float(v) for v in self.bbox_min],
            "bbox_max": [float(v) for v in self.bbox_max],
        }


@dataclass(frozen=True)
class QueryAnswer:
    """A query's ranking, split at the threshold: what passed, and the best of the rest with their scores.

    The candidates are there so that a person whose words matched nothing well still sees what came closest (and
    how close), instead of an empty answer; they are never counted as hits.
    """

    hits: list[QueryHit]  # best first: score >= min_score, or labelled with the class the query names
    candidates: list[QueryHit]  # best first: the highest-scoring instances that are not hits
    min_score: float


def rank_instances(
    instances: Sequence[InstanceInfo],
    vocabulary: Vocabulary,  # embeddings (L, D) unit rows
    query: str | np.ndarray,  # text, or a (D,) embedding
    *,
    feature_space: str,
    encoder: TextEncoder | None = None,
    top_k: int = 10,
    min_score: float = 0.5,
    candidates: int = 3,
    temperature: float | None = None,
    synonym_cos: float | None = None,
) -> QueryAnswer:
    """Every instance scored against a text or vector query, best first, split at ``min_score``.

    Args:
        instances: The scene's instances (their ``feature`` is the unit mean feature, ``(D,)``).
        vocabulary: The label set of the run, with embeddings ``(L, D)``.
        query: A class name (no encoder needed), any other text (encoded with ``encoder``), or a ``(D,)``
            vector.
        feature_space: ``features.space`` of the scene; picks the default encoder, temperature, synonym cut.
        encoder: Text encoder for free text; default ``get_text_encoder(feature_space)``.
        top_k: At most this many hits.
        min_score: Hits score at least this (0.5: the query beats the competing classes together).
        candidates: At most this many of the best instances that are not hits (0: none).
        temperature: Softmax temperature in cosine units; default ``label_sets.default_temperature``.
        synonym_cos: Near-synonym cut for free text and vectors; default ``SYNONYM_COS`` of the space.

    Returns:
        The hits (score >= ``min_score``, or labelled with the class a class-name query names; by descending
        score, ties: lower instance id first; at most ``top_k``) and the candidates (the best instances scoring
        under ``min_score`` that are not hits, in the same order, at most ``candidates``).

    Raises:
        InputError: empty text, vocabulary without embeddings, bad ``top_k`` / ``candidates`` / ``temperature``.
        ShapeError: vector or instance features not ``D``-dimensional.
        EncoderUnavailableError: free text but no encoder for the space.
    """
    if vocabulary.embeddings is None:
        raise InputError("query: the vocabulary has no embeddings (call language.label_sets.ensure_embeddings)")
    if top_k < 1:
        raise InputError(f"query: top_k must be >= 1, found {top_k}")
    if candidates < 0:
        raise InputError(f"query: candidates must be >= 0, found {candidates}")
    emb = _unit(np.asarray(vocabulary.embeddings, np.float32), name="vocabulary embeddings")
    q, own_class = _query_vector(query, vocabulary, emb, feature_space, encoder)
    if own_class is not None:  # the class itself is the query; every other class competes
        competitors, allies = np.delete(emb, own_class, axis=0), emb[:0]
    else:
        cut = synonym_cos if synonym_cos is not None else default_synonym_cos(feature_space, emb)
        near = emb @ q >= cut
        competitors, allies = emb[~near], emb[near]
    if not instances:
        return QueryAnswer(hits=[], candidates=[], min_score=min_score)
    temp = temperature if temperature is not None else default_temperature(feature_space, emb)
    if not temp > 0:
        raise InputError(f"query: temperature must be > 0, found {temp}")
    feats = _instance_features(instances, emb.shape[1])
    scores = query_scores(feats, q, competitors, temp, allies=allies)
    # A class-name query answers with every instance labelled with that class, whatever its softmax score:
    # labelling decided per primitive (and split clusters by class), while the score here uses the instance's
    # mean feature, which can fall just under min_score for a correctly labelled instance.
    labelled = np.array([own_class is not None and i.class_index == own_class for i in instances])
    order = np.lexsort((np.array([i.id for i in instances]), -scores, ~labelled))
    passed = [k for k in order if labelled[k] or scores[k] >= min_score][:top_k]
    taken = set(passed)
    # Below the threshold only (a passing instance that top_k cut is no candidate), by score alone.
    rest = [k for k in order if k not in taken and not labelled[k] and scores[k] < min_score]
    return QueryAnswer(
        hits=[_hit(instances[k], float(scores[k])) for k in passed],
        candidates=[_hit(instances[k], float(scores[k])) for k in rest[:candidates]],
        min_score=min_score,
    )


def query_instances(
    instances: Sequence[InstanceInfo],
    vocabulary: Vocabulary,  # embeddings (L, D) unit rows
    query: str | np.ndarray,  # text, or a (D,) embedding
    *,
    feature_space: str,
    encoder: TextEncoder | None = None,
    top_k: int = 10,
    min_score: float = 0.5,
    temperature: float | None = None,
    synonym_cos: float | None = None,
) -> list[QueryHit]:
    """The hits of ``rank_instances`` (same arguments, no candidates): instances at or above ``min_score``."""
    return rank_instances(
        instances,
        vocabulary,
        query,
        feature_space=feature_space,
        encoder=encoder,
        top_k=top_k,
        min_score=min_score,
        candidates=0,
        temperature=temperature,
        synonym_cos=synonym_cos,
    ).hits


def format_answer(label: str, answer: QueryAnswer) -> str:
    """The answer as ``panogs query`` prints it: the hits, or, when none passed, the best candidates with their
    scores and the threshold they missed (so that a person sees what came closest and what to lower)."""
    lines = []
    if answer.hits:
        lines.append(f"query {label}: {len(answer.hits)} instance(s)")
        lines += [_hit_line(hit) for hit in answer.hits]
    else:
        lines.append(f"query {label}: no instance scored at least {answer.min_score:g}")
        if answer.candidates:
            lines.append("  closest (below the threshold; --min-score lowers it):")
            lines += [_hit_line(hit) for hit in answer.candidates]
    return "\n".join(lines)


def _hit_line(hit: QueryHit) -> str:
    lo, hi = hit.bbox_min, hit.bbox_max
    return (
        f"  instance {hit.instance_id:>4}  {hit.class_name:<16} score {hit.score:.3f}  "
        f"box [{lo[0]:.2f} {lo[1]:.2f} {lo[2]:.2f}] - [{hi[0]:.2f} {hi[1]:.2f} {hi[2]:.2f}]"
    )


def query_scores(
    features: np.ndarray,  # (I, D) unit rows
    query: np.ndarray,  # (D,) unit
    competitors: np.ndarray,  # (C, D) unit rows
    temperature: float,
    *,
    allies: np.ndarray | None = None,  # (S, D) unit rows, near-synonym classes on the query's side
) -> np.ndarray:  # (I,) float64 in [0, 1]
    """Softmax over ``[query] + allies + competitors`` of cosine / temperature, summed over query and allies.

    Per instance, the probability that the query (or one of its near-synonym classes) beats the competitors.

    Example:
        >>> f = np.array([[1.0, 0.0], [0.0, 1.0]])
        >>> query_scores(f, np.array([1.0, 0.0]), np.array([[0.0, 1.0]]), 0.1).round(3).tolist()
        [1.0, 0.0]
    """
    side = query[None] if allies is None else np.concatenate([query[None], allies])
    ours = (features @ side.T).astype(np.float64) / temperature
    theirs = (features @ competitors.T).astype(np.float64) / temperature
    ours_lse = np.logaddexp.reduce(ours, axis=1)
    return np.exp(ours_lse - np.logaddexp.reduce(np.concatenate([ours, theirs], axis=1), axis=1))


def default_synonym_cos(feature_space: str, embeddings: np.ndarray) -> float:
    """Near-synonym cut: ``SYNONYM_COS`` of the space, else 0.9 raised above the closest pair of classes.

    Args:
        feature_space: ``features.space`` of the scene.
        embeddings: ``(L, D)`` unit rows of the vocabulary.
    """
    if feature_space in SYNONYM_COS:
        return SYNONYM_COS[feature_space]
    if len(embeddings) < 2:
        return DEFAULT_SYNONYM_COS
    sims = embeddings @ embeddings.T
    np.fill_diagonal(sims, -1.0)
    return max(DEFAULT_SYNONYM_COS, float(sims.max()) + 0.01)


def _query_vector(
    query: str | np.ndarray, vocabulary: Vocabulary, emb: np.ndarray, feature_space: str, encoder: TextEncoder | None
) -> tuple[np.ndarray, int | None]:
    """(unit query (D,), index of the vocabulary class it names or None)."""
    if isinstance(query, str):
        text = query.strip()
        if not text:
            raise InputError("query: empty text")
        lowered = [n.lower() for n in vocabulary.names]
        if text.lower() in lowered:
            index = lowered.index(text.lower())
            return emb[index], index
        if encoder is None:
            try:
                encoder = get_text_encoder(feature_space)
            except EncoderUnavailableError as exc:
                raise EncoderUnavailableError(
                    f"query {text!r} is not a class of the vocabulary ({', '.join(vocabulary.names)}) and "
                    f"cannot be encoded: {exc}"
                ) from exc
        vec = encode_labels(encoder, [text])[0]  # same prompt template as the vocabulary embeddings
    else:
        vec = np.asarray(query, np.float32)
        if vec.ndim == 2 and vec.shape[0] == 1:  # accept a (1, D) row as well
            vec = vec[0]
    if vec.shape != (emb.shape[1],):
        raise ShapeError(f"query vector: expected ({emb.shape[1]},) (the vocabulary's D), found {vec.shape}")
    return _unit(vec[None], name="query vector")[0], None


def _instance_features(instances: Sequence[InstanceInfo], dim: int) -> np.ndarray:  # (I, D) float32
    feats = np.stack([np.asarray(i.feature, np.float32).reshape(-1) for i in instances])
    if feats.shape[1] != dim:
        raise ShapeError(f"instance features: expected {dim}-d (the vocabulary's D), found {feats.shape[1]}-d")
    norms = np.linalg.norm(feats, axis=1, keepdims=True)
    return feats / np.maximum(norms, 1e-12)


def _unit(x: np.ndarray, *, name: str) -> np.ndarray:
    norms = np.linalg.norm(x, axis=-1, keepdims=True)
    if not np.all(np.isfinite(x)) or np.any(norms <= 1e-12):
        raise InputError(f"{name}: must be finite and non-zero")
    return (x / norms).astype(np.float32)


def _hit(info: InstanceInfo, score: float) -> QueryHit:
    return QueryHit(
        instance_id=int(info.id),
        class_name=info.class_name,
        score=min(max(score, 0.0), 1.0),
        centroid=np.asarray(info.centroid, np.float32),
        bbox_min=np.asarray(info.bbox_min, np.float32),
        bbox_max=np.asarray(info.bbox_max, np.float32),
    )
