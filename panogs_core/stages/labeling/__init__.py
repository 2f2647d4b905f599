"""Stage 8, semantic and panoptic labelling (docs/method.md §7).

Inputs: primitive positions, their unit language features, the graph-cut super-primitives (stage 5), the
clusters (stage 7) and a vocabulary with unit text embeddings. Output: :class:`PanopticLabels`, a class and an
instance id per primitive plus an :class:`InstanceInfo` (class, score, box, mean feature) per instance.

Steps:

1. Class per primitive = argmax cosine of its feature against the vocabulary embeddings (docs/method.md §7.1-7.2).
   Primitives with a zero feature (never seen, in the fused-feature ablation) have no evidence: class -1.
2. Optional vote inside each super-primitive (docs/method.md §7.3), guarded by purity (see ``LabelingConfig``).
3. Panoptic assembly. The reference stops at per-point classes and evaluates them against raw cluster ids;
   here each cluster's THING points become one instance with one class (the majority thing class of those
   points), and all points of one STUFF class become one instance (COCO panoptic convention).

Modules: ``config`` (settings), ``votes`` (class per primitive and the segment votes), ``unseen`` (primitives no key
frame saw), ``instances`` (panoptic assembly), ``output`` (the stage's output and ``instances.json``); this
module holds the entry point, :func:`assign_panoptic`, and re-exports the names other packages use.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from panogs_core.errors import InputError, NumericalError, ShapeError
from panogs_core.language.label_sets import default_temperature
from panogs_core.stages.labeling.config import LabelingConfig, point_spacing, scaled_to_spacing
from panogs_core.stages.labeling.instances import assemble, assemble_components, assemble_split, instance_infos
from panogs_core.stages.labeling.output import PanopticLabels, instances_to_json
from panogs_core.stages.labeling.unseen import NearestSeen, label_unseen, nearest_seen
from panogs_core.stages.labeling.votes import FusedEvidence, primitive_classes, vote_in_segments, vote_islands
from panogs_core.types import Vocabulary

__all__ = [
    "FusedEvidence",
    "LabelingConfig",
    "NearestSeen",
    "PanopticLabels",
    "assign_panoptic",
    "instances_to_json",
    "label_unseen",
    "nearest_seen",
    "point_spacing",
    "primitive_classes",
    "scaled_to_spacing",
    "unit_embeddings",
    "vote_in_segments",
    "vote_islands",
]


class _HasLabels(Protocol):
    """``SuperPrimitives`` / ``Clusters``: anything with a per-primitive ``labels`` array."""

    @property
    def labels(self) -> np.ndarray: ...  # (N,) int64


def assign_panoptic(
    points: np.ndarray,  # (N, 3) float32, world, metres
    features: np.ndarray,  # (N, D) float32, unit rows (zero rows = no evidence)
    superprimitives: _HasLabels,  # labels (N,) int64 dense in [0, S)
    clusters: _HasLabels,  # labels (N,) int64 in [0, K), -1 = removed
    vocabulary: Vocabulary,  # embeddings (L, D) unit rows
    cfg: LabelingConfig,
    *,
    neighbors: np.ndarray | None = None,  # (N, K) int64 kNN of the points (self excluded), or None
    fused: np.ndarray | FusedEvidence | None = None,  # (N, D) fused mean features (zero rows = unseen), or None
    nearest: NearestSeen | None = None,  # the unseen primitives' first graph search, made already, or None
) -> PanopticLabels:
    """Class and instance for every primitive, and the instance table.

    Args:
        points: Primitive positions. ``(N, 3)``.
        features: Language feature per primitive. ``(N, D)``.
        superprimitives: Graph-cut segments, used by the vote. ``labels (N,)``.
        clusters: Final clusters; -1 = removed small cluster. ``labels (N,)``.
        vocabulary: Label set with embeddings ``(L, D)``.
        cfg: Vote, minimum instance size, score temperature, class split.
        neighbors: kNN graph of ``points`` (self excluded) for the class split; built when None.
        fused: The fused mean features, or their :class:`FusedEvidence` (what the pipeline passes: it drops the
            ``(N, D)`` features once the field is fitted); None labels from ``features`` alone.
        nearest: :func:`nearest_seen` of ``points``, ``neighbors`` and the primitives ``fused`` says no key frame
            saw (the pipeline makes it beside the field's fit); used where the unseen primitives are those, else
            the search is made here.

    Returns:
        Per primitive: class (-1 = no evidence) and instance id (-1 = none). Thing instances: with
        ``cfg.split_classes`` see ``instances.assemble_split``; otherwise per cluster, the cluster's thing-class
        primitives, all relabelled to their majority thing class. Stuff instances:
        one per stuff class, every primitive of that class. Thing primitives of removed clusters (-1) keep
        their class and get no instance (they have no object to belong to); stuff primitives join their
        class's segment whatever their cluster. Instances smaller than ``cfg.min_instance_points`` are
        dissolved. Ids are dense: thing instances by cluster id first, then stuff by class index.

    Raises:
        ShapeError: arrays disagree on N, or features and embeddings on D.
        InputError: the vocabulary has no embeddings.
        NumericalError: non-finite features.
    """
    emb = _check_inputs(points, features, superprimitives.labels, clusters.labels, vocabulary)
    feats = np.asarray(features, dtype=np.float32)
    sq_norm = np.einsum("nd,nd->n", feats, feats)  # no (N, D) temporary: N x 512 float32 is 0.8 GB at 400k
    if not np.all(np.isfinite(sq_norm)):
        raise NumericalError("features: contain NaN or infinite values")
    field_sims = feats @ emb.T  # (N, L) cosines (rows of feats are unit or zero)
    segments = np.asarray(superprimitives.labels, np.int64)
    cluster = np.asarray(clusters.labels, np.int64)
    pts = np.asarray(points, np.float32)
    if neighbors is None and (cfg.split_classes or cfg.instances != "clusters" or fused is not None):
        from panogs_core.stages.neighbors import build_knn

        neighbors = build_knn(points, min(cfg.split_neighbors, max(len(pts) - 1, 1))).neighbors
    nbr = None if neighbors is None else np.asarray(neighbors, np.int64)
    if nbr is not None and cfg.reference_spacing is not None:
        cfg = scaled_to_spacing(cfg, point_spacing(pts, nbr))
    unseen_counts: dict[str, int] = {}
    temperature = cfg.score_temperature or default_temperature(None, emb)
    scores = field_sims
    seen = None  # (N,) bool primitives some key frame saw; None without the fused features
    if fused is None:
        # DEPARTURE (a zero feature has no evidence: class -1, not class 0 by accident of argmax): docs/method.md §7.2.
        cls = np.where(sq_norm > 1e-12, np.argmax(field_sims, axis=1), -1).astype(np.int64)
    else:
        evidence = fused if isinstance(fused, FusedEvidence) else FusedEvidence.of(np.asarray(fused, np.float32), emb)
        if evidence.cosines.shape != field_sims.shape:
            raise ShapeError(f"fused: expected cosines of shape {field_sims.shape}, found {evidence.cosines.shape}")
        cls, scores = primitive_classes(field_sims, evidence, cfg)
        seen = cls >= 0  # -1 exactly where no key frame saw the primitive (a zero fused feature)
    if cfg.vote == "superprimitive":
        cls = vote_in_segments(cls, segments, cfg.vote_min_fraction)
    elif cfg.vote == "islands" and nbr is not None:
        margin = None
        if cfg.vote_max_ratio > 0:  # the score gap a flip may cross: T ln(1 / ratio) in cosine units
            margin = temperature * np.log(1.0 / cfg.vote_max_ratio)
        cls = vote_islands(cls, segments, nbr, cfg.island_points, cfg.vote_min_fraction, scores, margin)
    if fused is not None and nbr is not None:
        lead = temperature * float(np.log(cfg.unseen_field_ratio))  # the field's lead that overrules a segment
        cls, unseen_counts = label_unseen(cls, field_sims, pts, nbr, segments, cfg.unseen, lead, nearest)
    if cfg.instances != "clusters" and nbr is not None:
        semantic, instance, inst_class = assemble_components(cls, cluster, vocabulary.is_thing, pts, nbr, cfg, seen)
    elif cfg.split_classes and nbr is not None:
        semantic, instance, inst_class = assemble_split(cls, cluster, vocabulary.is_thing, cfg.min_instance_points, nbr)
    else:
        semantic, instance, inst_class = assemble(cls, cluster, vocabulary.is_thing, cfg.min_instance_points)
    infos = instance_infos(pts, feats, field_sims / temperature, instance, inst_class, vocabulary)
    return PanopticLabels(semantic=semantic, instance=instance, instances=infos, unseen=unseen_counts)


def _check_inputs(
    points: np.ndarray, features: np.ndarray, sp_labels: np.ndarray, cl_labels: np.ndarray, vocabulary: Vocabulary
) -> np.ndarray:  # (L, D) float32 unit
    emb = unit_embeddings(vocabulary)
    n = np.shape(points)[0] if np.ndim(points) == 2 else -1
    if np.shape(points) != (n, 3) or n < 0:
        raise ShapeError(f"points: expected (N, 3), found {np.shape(points)}")
    if np.shape(features) != (n, emb.shape[1]):
        raise ShapeError(f"features: expected ({n}, {emb.shape[1]}) (N, vocabulary D), found {np.shape(features)}")
    for name, lab in (("superprimitives.labels", sp_labels), ("clusters.labels", cl_labels)):
        if np.shape(lab) != (n,):
            raise ShapeError(f"{name}: expected ({n},), found {np.shape(lab)}")
    if np.any(np.asarray(sp_labels) < 0):
        raise InputError("superprimitives.labels: expected ids >= 0 (dense, no void)")
    return emb


def unit_embeddings(vocabulary: Vocabulary) -> np.ndarray:  # (L, D) float32 unit rows
    """The vocabulary's class embeddings scaled to unit length, as :func:`assign_panoptic` scores with them."""
    if vocabulary.embeddings is None:
        raise InputError(
            "assign_panoptic: the vocabulary has no embeddings (call language.label_sets.ensure_embeddings)"
        )
    emb = np.asarray(vocabulary.embeddings, np.float32)
    return emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12)
