"""Write a run's outputs; compute metrics when there is ground truth.

The files, their names and what each holds are declared once, in :mod:`panogs_core.io.run_folder` (``RUN_FILES``;
docs/architecture.md, "Outputs of a run", is generated from it). ``panoptic.ply``'s red/green/blue colour the
panoptic segmentation (one colour per instance, stuff by class) so that it reads at a glance in any PLY viewer;
the captured colours are in ``gaussians.ply``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.gaussians.config import GaussianScene, initial_gaussians
from panogs_core.io.bundle import Bundle
from panogs_core.io.ply import write_ply
from panogs_core.io.run_folder import (
    CAMERAS_JSON,
    GAUSSIANS_PLY,
    INSTANCE_FEATURES_NPY,
    INSTANCES_JSON,
    LABELS_NPZ,
    METRICS_JSON,
    PANOPTIC_PLY,
    VOCABULARY_JSON,
    VOCABULARY_NPY,
)
from panogs_core.palette import panoptic_colors
from panogs_core.stages.clustering import Clusters
from panogs_core.stages.fusion import FusedFeatures
from panogs_core.stages.labeling import PanopticLabels
from panogs_core.stages.primitives import Primitives
from panogs_core.stages.superprimitives import SuperPrimitives
from panogs_core.types import Vocabulary


def write_vocabulary(out: Path, vocab: Vocabulary, feature_space: str) -> dict[str, Path]:
    """``vocabulary.json`` (bundle format + ``space``) and ``vocabulary.npy``; returns the paths written."""
    classes = [{"name": n, "kind": k} for n, k in zip(vocab.names, vocab.kinds, strict=True)]
    doc: dict[str, Any] = {"classes": classes, "space": feature_space}
    files = {VOCABULARY_JSON.name: VOCABULARY_JSON.path(out)}
    if vocab.embeddings is not None:
        files[VOCABULARY_NPY.name] = VOCABULARY_NPY.path(out)
        np.save(files[VOCABULARY_NPY.name], np.asarray(vocab.embeddings, dtype=np.float32))
        doc["embeddings"] = VOCABULARY_NPY.name
    files[VOCABULARY_JSON.name].write_text(json.dumps(doc, indent=1))
    return files


def write_gaussians(
    path: Path,
    prims: Primitives,
    colors: np.ndarray,  # (N, 3) in [0, 1], used when the scene was not fitted
    semantic: np.ndarray,
    instance: np.ndarray,
    gaussians: GaussianScene | None = None,
) -> None:
    """``gaussians.ply``: the fitted scene, or the initialisation with ``colors`` (panogs_core/gaussians/ply.py)."""
    from panogs_core.gaussians.ply import write_gaussian_ply

    if gaussians is None or not gaussians.fitted:
        gaussians = initial_gaussians(prims, colors)
    write_gaussian_ply(path, gaussians, np.asarray(prims.normals, np.float32), semantic, instance)


def primitive_colors(prims: Primitives, fused: FusedFeatures) -> np.ndarray:  # (N, 3) float32 in [0, 1]
    """Colours of the geometry, else those fused from the colour frames, else mid grey."""
    if prims.colors is not None:
        return np.asarray(prims.colors, dtype=np.float32)
    if fused.colors is not None:
        return np.asarray(fused.colors, dtype=np.float32)
    return np.full((prims.points.shape[0], 3), 0.5, np.float32)


def write_outputs(
    out: Path,
    scene: Bundle,
    prims: Primitives,
    fused: FusedFeatures,
    superprimitives: SuperPrimitives,
    clusters: Clusters,
    labels: PanopticLabels,
    vocab: Vocabulary,
    *,
    gaussians: GaussianScene | None = None,
) -> tuple[dict[str, Path], dict[str, Any] | None]:
    """Write every output file; returns their paths and the metrics (None without ground truth)."""
    files: dict[str, Path] = {}
    semantic = np.asarray(labels.semantic, dtype=np.int64)
    instance = np.asarray(labels.instance, dtype=np.int64)
    pts = np.asarray(prims.points, dtype=np.float32)

    rgb = panoptic_colors(semantic, instance, vocab.is_thing)
    files[PANOPTIC_PLY.name] = PANOPTIC_PLY.path(out)
    write_ply(
        files[PANOPTIC_PLY.name],
        {
            "x": pts[:, 0],
            "y": pts[:, 1],
            "z": pts[:, 2],
            "red": rgb[:, 0],
            "green": rgb[:, 1],
            "blue": rgb[:, 2],
            "semantic": semantic.astype(np.int32),
            "instance": instance.astype(np.int32),
        },
    )
    files[LABELS_NPZ.name] = LABELS_NPZ.path(out)
    np.savez_compressed(
        files[LABELS_NPZ.name],
        semantic=semantic,
        instance=instance,
        superprimitive=np.asarray(superprimitives.labels, dtype=np.int64),
        cluster=np.asarray(clusters.labels, dtype=np.int64),
        class_names=np.array(vocab.names),
    )
    instances = [i.to_json() for i in labels.instances]
    files[INSTANCES_JSON.name] = INSTANCES_JSON.path(out)
    files[INSTANCES_JSON.name].write_text(json.dumps(instances, indent=1))
    dim = vocab.embeddings.shape[1] if vocab.embeddings is not None else 0
    feats = (
        np.stack([np.asarray(i.feature, np.float32) for i in labels.instances])
        if instances
        else np.zeros((0, dim), np.float32)
    )
    files[INSTANCE_FEATURES_NPY.name] = INSTANCE_FEATURES_NPY.path(out)
    np.save(files[INSTANCE_FEATURES_NPY.name], feats)
    files.update(write_vocabulary(out, vocab, scene.feature_space))
    files[GAUSSIANS_PLY.name] = GAUSSIANS_PLY.path(out)
    write_gaussians(files[GAUSSIANS_PLY.name], prims, primitive_colors(prims, fused), semantic, instance, gaussians)
    from panogs_core.gaussians.views import write_cameras
    from panogs_core.stages.up_direction import run_up

    poses = [f.T_world_cam for f in scene.frames] + [pose for _, pose in scene.skipped_poses]
    up = run_up(scene.up, poses, np.asarray(prims.normals))
    files[CAMERAS_JSON.name] = write_cameras(
        CAMERAS_JSON.path(out), scene.camera, scene.frames, up=up.up, up_source=up.source, skipped=scene.skipped_poses
    )

    metrics = compute_metrics(scene, pts, semantic, instance, vocab)
    if metrics is not None:
        files[METRICS_JSON.name] = METRICS_JSON.path(out)
        files[METRICS_JSON.name].write_text(json.dumps(metrics, indent=2))
    return files, metrics


def compute_metrics(
    scene: Bundle, points: np.ndarray, semantic: np.ndarray, instance: np.ndarray, vocab: Vocabulary
) -> dict[str, Any] | None:
    """Standard and paper metrics against ``gt/labels.npz``; None when there is no usable ground truth.

    Ground truth indexes the bundle's own vocabulary, so a run with another vocabulary is not scored.
    Ground truth on other points than the primitives takes the prediction of the nearest primitive.
    """
    from panogs_core.evaluation.metrics import evaluate_ground_truth

    gt = scene.read_ground_truth() if scene.has_ground_truth else None
    if gt is None or scene.vocabulary is None or tuple(scene.vocabulary.names) != tuple(vocab.names):
        return None
    if gt.points is None and gt.semantic.shape[0] != semantic.shape[0]:
        return None  # per-vertex ground truth but the primitives are not the geometry's vertices
    metrics = evaluate_ground_truth(points, semantic, instance, gt, vocab)
    return {mode: m.to_json() for mode, m in metrics.items()}
