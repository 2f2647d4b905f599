"""Glue between :mod:`panogs_core.pipeline` and the stage modules: one call per stage, checkpoint I/O and keys.

Kept apart from ``pipeline.py`` so the orchestration reads as the list of stages, and so each stage's imports
(torch, open3d) happen only when that stage runs.
"""

from __future__ import annotations

import hashlib
import importlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.bundle import Scene
from panogs_core.config import PipelineConfig
from panogs_core.progress import ProgressFn
from panogs_core.types import Vocabulary


def _key(*parts: Any) -> str:
    blob = json.dumps(parts, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:20]


def _vocabulary_hash(vocab: Vocabulary) -> str:
    digest = hashlib.sha256(json.dumps([vocab.names, vocab.kinds]).encode())
    if vocab.embeddings is not None:
        digest.update(np.ascontiguousarray(vocab.embeddings, dtype=np.float32).tobytes())
    return digest.hexdigest()[:20]


def stage_keys(input_hash: str, cfg: PipelineConfig, vocab: Vocabulary) -> dict[str, str]:
    """Checkpoint key per stage: its config section plus the keys of everything it depends on."""
    c = cfg.to_dict()
    k: dict[str, str] = {}
    k["primitives"] = _key(input_hash, c["primitives"])
    k["appearance"] = _key(k["primitives"], c["appearance"])
    k["visibility"] = _key(k["primitives"], c["visibility"], "with-depth-residual")  # older checkpoints lack it
    k["fusion"] = _key(k["visibility"], c["fusion"])
    k["language_field"] = _key(k["fusion"], c["language_field"])
    features_key = k["language_field"] if cfg.features_source == "field" else k["fusion"]
    k["features"] = _key(features_key, cfg.features_source)
    k["masks"] = _key(k["visibility"], c["affinity"])
    k["superprimitives"] = _key(k["primitives"], k["features"], k["masks"], c["superprimitives"])
    k["clustering"] = _key(k["superprimitives"], k["masks"], k["features"], c["affinity"], c["clustering"])
    k["labeling"] = _key(k["clustering"], k["features"], _vocabulary_hash(vocab), c["labeling"])
    return k


@dataclass(frozen=True)
class GraphStage:
    """Super-primitives with the kNN graph they were cut from (the clustering reuses that graph)."""

    superprimitives: Any  # SuperPrimitives
    knn: Any  # KnnGraph

    def save(self, path: Path) -> None:
        np.savez(path, labels=self.superprimitives.labels, neighbors=self.knn.neighbors, distances=self.knn.distances)

    @classmethod
    def load(cls, path: Path) -> GraphStage:
        from panogs_core.superprimitives import KnnGraph, SuperPrimitives

        with np.load(path, allow_pickle=False) as z:
            return cls(
                SuperPrimitives(labels=z["labels"]), KnnGraph(neighbors=z["neighbors"], distances=z["distances"])
            )


# Checkpoint class of each stage, as (module, class name): imported only when that stage is loaded or saved.
_CHECKPOINT_CLASSES = {
    "primitives": ("panogs_core.primitives", "Primitives"),
    "appearance": ("panogs_core.appearance", "GaussianScene"),
    "visibility": ("panogs_core.visibility", "Visibility"),
    "fusion": ("panogs_core.fusion", "FusedFeatures"),
    "language_field": ("panogs_core.language_field", "LanguageField"),
    "superprimitives": ("panogs_core.stages", "GraphStage"),
    "masks": ("panogs_core.affinity", "MaskObservations"),
    "clustering": ("panogs_core.clustering", "Clusters"),
    "labeling": ("panogs_core.labeling", "PanopticLabels"),
}


def io_for(stage: str) -> tuple[Callable[[Path], Any], Callable[[Any, Path], None]]:
    """(load, save) of a stage's checkpoint."""
    module, name = _CHECKPOINT_CLASSES[stage]

    def load(path: Path) -> Any:
        return getattr(importlib.import_module(module), name).load(path)

    return load, (lambda obj, path: obj.save(path))


def primitives(scene: Scene, cfg: PipelineConfig, progress: ProgressFn) -> Any:
    from panogs_core.primitives import build_primitives

    return build_primitives(scene, cfg.primitives, on_progress=progress)


def appearance(scene: Scene, prims: Any, cfg: PipelineConfig, progress: ProgressFn) -> Any:
    """The Gaussian scene fitted to the colour frames, from the primitives' colours (grey where they have none:
    fused colours come later, and the fit learns the colour anyway)."""
    from panogs_core.appearance import fit_appearance

    colors = prims.colors if prims.colors is not None else np.full((prims.points.shape[0], 3), 0.5, np.float32)
    return fit_appearance(scene, prims, colors, cfg.appearance, on_progress=progress)


def visibility(scene: Scene, prims: Any, cfg: PipelineConfig, progress: ProgressFn) -> Any:
    from panogs_core.visibility import compute_visibility

    return compute_visibility(scene, prims.points, cfg.visibility, on_progress=progress)


def fusion(scene: Scene, vis: Any, prims: Any, cfg: PipelineConfig, progress: ProgressFn) -> Any:
    from panogs_core.fusion import fuse_features

    return fuse_features(scene, vis, int(prims.points.shape[0]), cfg.fusion, on_progress=progress)


def language_field(prims: Any, fused: Any, cfg: PipelineConfig, progress: ProgressFn) -> Any:
    if cfg.features_source == "fused":
        return None  # the ablation skips the field entirely
    from panogs_core.language_field import fit_language_field

    return fit_language_field(prims.points, fused, cfg.language_field, on_progress=progress)


def primitive_features(field: Any, fused: Any, cfg: PipelineConfig) -> np.ndarray:  # (N, D) float32 unit
    """The per-primitive language features used downstream: decoded field, or the fused means."""
    if cfg.features_source == "field" and field is not None:
        return np.asarray(field.features, dtype=np.float32)
    feats = np.asarray(fused.features, dtype=np.float32)
    norms = np.linalg.norm(feats, axis=1, keepdims=True)
    return feats / np.maximum(norms, 1e-12)


def superprimitives(
    prims: Any, features: np.ndarray, masks: Any, cfg: PipelineConfig, progress: ProgressFn
) -> GraphStage:
    from panogs_core.superprimitives import build_knn, graph_cut_superprimitives

    knn = build_knn(prims.points, cfg.superprimitives.k_neighbors)
    feats = features if cfg.superprimitives.use_language else None
    sp = graph_cut_superprimitives(
        prims.points, prims.normals, feats, knn, cfg.superprimitives, masks=masks, on_progress=progress
    )
    return GraphStage(sp, knn)


def masks(scene: Scene, vis: Any, cfg: PipelineConfig, progress: ProgressFn) -> Any:
    from panogs_core.affinity import observe_masks

    return observe_masks(scene, vis, cfg.affinity, on_progress=progress)


def clustering(
    graph: GraphStage, observations: Any, features: np.ndarray, cfg: PipelineConfig, progress: ProgressFn
) -> Any:
    from panogs_core.clustering import progressive_clustering

    return progressive_clustering(
        graph.superprimitives,
        graph.knn,
        observations,
        cfg.clustering,
        cfg.affinity,
        features=features,
        on_progress=progress,
    )


def labeling(
    prims: Any,
    features: np.ndarray,
    fused: Any,
    graph: GraphStage,
    clusters: Any,
    vocab: Vocabulary,
    cfg: PipelineConfig,
) -> Any:
    from panogs_core.labeling import assign_panoptic

    return assign_panoptic(
        prims.points,
        features,
        graph.superprimitives,
        clusters,
        vocab,
        cfg.labeling,
        neighbors=graph.knn.neighbors,
        fused=np.asarray(fused.features, np.float32),
    )
