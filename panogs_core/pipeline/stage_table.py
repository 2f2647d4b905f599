"""Glue between :mod:`panogs_core.pipeline.run` and the stage modules: the stage table, one call per stage, and keys.

Kept apart from ``pipeline/run.py`` so the orchestration reads as the list of stages. Importing this module imports
the stage modules, which are light (numpy, scipy): each imports torch or open3d only inside the function that
needs it, so a stage's heavy imports still happen only when that stage runs.

A checkpointed stage is a :class:`StageSpec`: its name, how its output is read back, and what its checkpoint key
covers, namely the keys of the stages it reads and exactly the settings it reads (never a whole config section
that other stages share), so that changing one stage's setting redoes that stage and those after it, no more.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, Protocol, TypeVar

import numpy as np

from panogs_core.gaussians import GaussianScene, fit_appearance
from panogs_core.io.bundle import Bundle
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.snapshots import StageSnapshot
from panogs_core.progress import ProgressFn
from panogs_core.stages.affinity import AffinityConfig, segment_affinity
from panogs_core.stages.clustering import Clusters, progressive_clustering
from panogs_core.stages.fusion import FusedFeatures, fuse_features
from panogs_core.stages.labeling import FusedEvidence, PanopticLabels, assign_panoptic, unit_embeddings
from panogs_core.stages.language_field import LanguageField, fit_language_field
from panogs_core.stages.masks import MaskObservations, observe_masks
from panogs_core.stages.neighbors import KnnGraph, build_knn
from panogs_core.stages.primitives import Primitives, build_primitives
from panogs_core.stages.superprimitives import SuperPrimitives, graph_cut_superprimitives
from panogs_core.stages.visibility import Visibility, compute_visibility
from panogs_core.types import Vocabulary


class Checkpoint(Protocol):
    """A stage output that writes itself to one ``.npz`` (its class's ``load`` reads it back)."""

    def save(self, path: Path) -> None: ...


C = TypeVar("C", bound=Checkpoint)


@dataclass(frozen=True)
class StageSpec(Generic[C]):
    """A checkpointed stage of the pipeline.

    Attributes:
        name: The stage's name in ``pipeline.STAGES``, ``report.json`` and ``stages/manifest.json``.
        load: Reads the stage's checkpoint back (the output class's ``load``).
        inputs: The keys its key includes: upstream stages, or ``"input"`` (the bundle's hash), ``"features"``
            (the per-primitive language features, see :func:`primitive_features`), ``"vocabulary"``.
        settings: Exactly the settings the stage reads, from the pipeline config.
    """

    name: str
    load: Callable[[Path], C]
    inputs: tuple[str, ...]
    settings: Callable[[PipelineConfig], object]

    def key(self, keys: Mapping[str, str], cfg: PipelineConfig) -> str:
        """Checkpoint key: a hash of the input keys and the settings."""
        return _key(*(keys[name] for name in self.inputs), self.settings(cfg))


def _affinity_measure(cfg: AffinityConfig) -> dict[str, object]:
    """The affinity settings the clustering reads: all but the two the mask look-ups read (same YAML section)."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg) if not f.name.startswith("mask_")}


PRIMITIVES = StageSpec("primitives", Primitives.load, ("input",), lambda c: c.primitives)
# Reads the colour frames (covered by "input" through the primitives' key) and its own settings.
APPEARANCE = StageSpec("appearance", GaussianScene.load, ("primitives",), lambda c: c.appearance)
# "with-depth-residual": checkpoints written before Visibility carried depth residuals must not be reused.
VISIBILITY = StageSpec("visibility", Visibility.load, ("primitives",), lambda c: (c.visibility, "with-depth-residual"))
FUSION = StageSpec("fusion", FusedFeatures.load, ("visibility",), lambda c: c.fusion)
LANGUAGE_FIELD = StageSpec("language_field", LanguageField.load, ("fusion",), lambda c: c.language_field)
MASKS = StageSpec("masks", MaskObservations.load, ("visibility",), lambda c: c.affinity.mask_lookup())
NEIGHBORS = StageSpec("neighbors", KnnGraph.load, ("primitives",), lambda c: c.superprimitives.k_neighbors)
SUPERPRIMITIVES = StageSpec(
    "superprimitives",
    SuperPrimitives.load,
    ("primitives", "features", "masks", "neighbors"),
    lambda c: c.superprimitives,
)
CLUSTERING = StageSpec(
    "clustering",
    Clusters.load,
    ("superprimitives", "neighbors", "masks", "features"),
    lambda c: (c.clustering, _affinity_measure(c.affinity)),
)
LABELING = StageSpec(
    "labeling",
    PanopticLabels.load,
    ("clustering", "superprimitives", "neighbors", "features", "fusion", "vocabulary"),
    lambda c: c.labeling,
)


def _plain(obj: object) -> object:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    return str(obj)


def _key(*parts: object) -> str:
    blob = json.dumps(parts, sort_keys=True, default=_plain).encode()
    return hashlib.sha256(blob).hexdigest()[:20]


def _vocabulary_hash(vocab: Vocabulary) -> str:
    digest = hashlib.sha256(json.dumps([vocab.names, vocab.kinds]).encode())
    if vocab.embeddings is not None:
        digest.update(np.ascontiguousarray(vocab.embeddings, dtype=np.float32).tobytes())
    return digest.hexdigest()[:20]


def stage_keys(input_hash: str, cfg: PipelineConfig, vocab: Vocabulary) -> dict[str, str]:
    """Checkpoint key of every checkpointed stage (and of the inputs they name), in pipeline order."""
    keys = {"input": input_hash, "vocabulary": _vocabulary_hash(vocab)}
    for upstream in (PRIMITIVES, APPEARANCE, VISIBILITY, FUSION, LANGUAGE_FIELD):
        keys[upstream.name] = upstream.key(keys, cfg)
    features_from = LANGUAGE_FIELD if cfg.features_source == "field" else FUSION
    keys["features"] = _key(keys[features_from.name], cfg.features_source)
    for downstream in (MASKS, NEIGHBORS, SUPERPRIMITIVES, CLUSTERING, LABELING):
        keys[downstream.name] = downstream.key(keys, cfg)
    return keys


def primitives(bundle: Bundle, cfg: PipelineConfig, progress: ProgressFn) -> Primitives:

    return build_primitives(bundle, cfg.primitives, on_progress=progress)


def appearance(
    bundle: Bundle, prims: Primitives, cfg: PipelineConfig, progress: ProgressFn, snapshot: StageSnapshot | None = None
) -> GaussianScene:
    """The Gaussian scene fitted to the colour frames, from the primitives' colours (grey where they have none:
    fused colours come later, and the fit learns the colour anyway)."""
    colors = prims.colors if prims.colors is not None else np.full((prims.points.shape[0], 3), 0.5, np.float32)
    return fit_appearance(bundle, prims, colors, cfg.appearance, on_progress=progress, snapshot=snapshot)


def visibility(bundle: Bundle, prims: Primitives, cfg: PipelineConfig, progress: ProgressFn) -> Visibility:

    return compute_visibility(bundle, prims.points, cfg.visibility, on_progress=progress)


def fusion(
    bundle: Bundle, vis: Visibility, prims: Primitives, cfg: PipelineConfig, progress: ProgressFn
) -> FusedFeatures:
    """The fused features; colours only for primitives that have none of their own (the export reads the
    geometry's first, so fusing them would read every colour frame for nothing). The input's hash, in the key,
    says which."""
    settings = cfg.fusion if prims.colors is None else dataclasses.replace(cfg.fusion, fuse_colors=False)
    return fuse_features(bundle, vis, int(prims.points.shape[0]), settings, on_progress=progress)


def language_field(prims: Primitives, fused: FusedFeatures, cfg: PipelineConfig, progress: ProgressFn) -> LanguageField:

    return fit_language_field(prims.points, fused, cfg.language_field, on_progress=progress)


def primitive_features(field: LanguageField | None, fused: FusedFeatures) -> np.ndarray:  # (N, D) float32 unit
    """The per-primitive language features used downstream: the decoded field, or (no field) the fused means."""
    if field is not None:
        return np.asarray(field.features, dtype=np.float32)
    feats = np.asarray(fused.features, dtype=np.float32)
    norms = np.linalg.norm(feats, axis=1, keepdims=True)
    return feats / np.maximum(norms, 1e-12)


def fused_evidence(fused: FusedFeatures, vocab: Vocabulary) -> FusedEvidence:
    """What the labelling reads of the fused features (``(N, L)`` cosines and the seen rows), so that the pipeline
    can drop the ``(N, D)`` features once the field is fitted."""
    return FusedEvidence.of(np.asarray(fused.features, np.float32), unit_embeddings(vocab))


def masks(bundle: Bundle, vis: Visibility, cfg: PipelineConfig, progress: ProgressFn) -> MaskObservations:

    return observe_masks(bundle, vis, cfg.affinity.mask_lookup(), on_progress=progress)


def neighbors(prims: Primitives, cfg: PipelineConfig) -> KnnGraph:

    return build_knn(prims.points, cfg.superprimitives.k_neighbors)


def superprimitives(
    prims: Primitives,
    features: np.ndarray,
    observations: MaskObservations,
    knn: KnnGraph,
    cfg: PipelineConfig,
    progress: ProgressFn,
) -> SuperPrimitives:

    feats = features if cfg.superprimitives.use_language else None
    return graph_cut_superprimitives(
        prims.points, prims.normals, feats, knn, cfg.superprimitives, masks=observations, on_progress=progress
    )


def clustering(
    sp: SuperPrimitives,
    knn: KnnGraph,
    observations: MaskObservations,
    features: np.ndarray,
    cfg: PipelineConfig,
    progress: ProgressFn,
) -> Clusters:

    affinity = segment_affinity(sp.labels, observations, cfg.affinity, features=features)
    return progressive_clustering(sp, knn, affinity, cfg.clustering, on_progress=progress)


def labeling(
    prims: Primitives,
    features: np.ndarray,
    fused: FusedEvidence,
    sp: SuperPrimitives,
    knn: KnnGraph,
    clusters: Clusters,
    vocab: Vocabulary,
    cfg: PipelineConfig,
) -> PanopticLabels:

    return assign_panoptic(
        prims.points,
        features,
        sp,
        clusters,
        vocab,
        cfg.labeling,
        neighbors=knn.neighbors,
        fused=fused,
    )
