"""Read a finished run's folder back for queries, without the pipeline and without torch.

Needs ``instances.json``, ``instance_features.npy`` and ``vocabulary.json`` (+ ``vocabulary.npy``), all written by
:func:`panogs_core.export.write_outputs`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panogs_core.errors import InputError
from panogs_core.labeling import InstanceInfo
from panogs_core.types import Vocabulary


@dataclass(frozen=True)
class LoadedResult:
    """What a query needs from a run."""

    instances: tuple[InstanceInfo, ...]
    vocabulary: Vocabulary
    feature_space: str


def _read_json(path: Path) -> object:
    if not path.is_file():
        raise InputError(f"{path}: missing; is {path.parent} the --out folder of a finished run?")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from exc


def load_vocabulary(out_dir: Path) -> tuple[Vocabulary, str]:
    """The run's vocabulary (with embeddings) and its feature space."""
    doc = _read_json(out_dir / "vocabulary.json")
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
    rows = _read_json(out / "instances.json")
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
