"""Read a finished run's folder back for queries and evaluation, without the pipeline and without torch.

Queries need ``instances.json``, ``instance_features.npy`` and ``vocabulary.json`` (+ ``vocabulary.npy``);
evaluation needs ``labels.npz``, ``panoptic.ply`` (the primitive positions) and ``vocabulary.json``. All are written
by :func:`panogs_core.stages.export.write_outputs`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.ply import read_ply_vertices
from panogs_core.io.run_json import read_run_json
from panogs_core.stages.labeling import InstanceInfo
from panogs_core.types import Vocabulary


@dataclass(frozen=True)
class LoadedResult:
    """What a query needs from a run."""

    instances: tuple[InstanceInfo, ...]
    vocabulary: Vocabulary
    feature_space: str


@dataclass(frozen=True)
class RunLabels:
    """What evaluation needs from a run: the labelled primitives and the classes their labels index."""

    points: np.ndarray  # (N, 3) float32, primitive positions
    semantic: np.ndarray  # (N,) int64, -1 void
    instance: np.ndarray  # (N,) int64, -1 none
    vocabulary: Vocabulary


def load_vocabulary(out_dir: Path) -> tuple[Vocabulary, str]:
    """The run's vocabulary (with embeddings) and its feature space."""
    doc = read_run_json(out_dir / "vocabulary.json")
    assert isinstance(doc, dict)
    classes = doc.get("classes", [])
    embeddings = None
    if doc.get("embeddings"):
        embeddings = np.load(out_dir / str(doc["embeddings"]), allow_pickle=False).astype(np.float32)
    vocab = Vocabulary(
        names=tuple(c["name"] for c in classes), kinds=tuple(c["kind"] for c in classes), embeddings=embeddings
    )
    return vocab, str(doc.get("space", ""))


def load_result(out_dir: str | Path) -> LoadedResult:
    """Instances (with their features), vocabulary and feature space of a finished run.

    Raises:
        InputError: a file is missing or does not match the others.
    """
    out = Path(out_dir)
    vocab, space = load_vocabulary(out)
    rows = read_run_json(out / "instances.json")
    assert isinstance(rows, list)
    feats_path = out / "instance_features.npy"
    if not feats_path.is_file():
        raise InputError(f"{feats_path}: missing; is {out} the --out folder of a finished run?")
    feats = np.load(feats_path, allow_pickle=False).astype(np.float32)
    if feats.shape[0] != len(rows):
        raise InputError(f"{feats_path}: {feats.shape[0]} rows but instances.json lists {len(rows)} instances")
    instances = tuple(
        InstanceInfo(
            id=int(r["id"]),
            class_index=int(r["class_index"]),
            class_name=str(r["class_name"]),
            kind=str(r["kind"]),
            score=float(r["score"]),
            num_points=int(r["num_points"]),
            centroid=np.asarray(r["centroid"], np.float32),
            bbox_min=np.asarray(r["bbox_min"], np.float32),
            bbox_max=np.asarray(r["bbox_max"], np.float32),
            feature=feats[i],
        )
        for i, r in enumerate(rows)
    )
    return LoadedResult(instances=instances, vocabulary=vocab, feature_space=space)


def load_run_labels(out_dir: str | Path) -> RunLabels:
    """Primitive positions (``panoptic.ply``), labels (``labels.npz``) and vocabulary of a finished run.

    Raises:
        InputError: a file is missing, unreadable, or does not match the others.
    """
    out = Path(out_dir)
    vocab, _ = load_vocabulary(out)
    labels_path, ply_path = out / "labels.npz", out / "panoptic.ply"
    for path in (labels_path, ply_path):
        if not path.is_file():
            raise InputError(f"{path}: missing; is {out} the --out folder of a finished run?")
    try:
        with np.load(labels_path, allow_pickle=False) as npz:
            semantic, instance = npz["semantic"].astype(np.int64), npz["instance"].astype(np.int64)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"{labels_path}: expected semantic and instance arrays ({exc})") from exc
    vertices = read_ply_vertices(ply_path)
    if not {"x", "y", "z"} <= vertices.keys():
        raise InputError(f"{ply_path}: vertex properties {sorted(vertices)}, expected x, y, z")
    points = np.stack([vertices[k] for k in "xyz"], axis=1).astype(np.float32)
    if not (len(points) == len(semantic) == len(instance)):
        raise InputError(
            f"{labels_path}: semantic {semantic.shape}, instance {instance.shape}, expected ({len(points)},) "
            f"(the vertices of {ply_path.name})"
        )
    return RunLabels(points=points, semantic=semantic, instance=instance, vocabulary=vocab)
