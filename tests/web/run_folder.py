"""A small finished run folder written directly (no pipeline): what the viewer reads from a run."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.gaussians.config import SH_C0, GaussianScene
from panogs_core.gaussians.ply import write_gaussian_ply
from panogs_core.io.run_folder import GAUSSIANS_PLY

CLASSES = [("wall", "stuff"), ("chair", "thing"), ("table", "thing")]


def write_run(out: Path, n: int = 60, dim: int = 8) -> dict[str, Any]:
    """Three instances (one per class) over ``n`` primitives, 5 of them unlabelled; returns the source arrays."""
    rng = np.random.default_rng(1)
    out.mkdir(parents=True, exist_ok=True)
    points = rng.uniform(0, 4, (n, 3)).astype(np.float32)
    colors = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    log_scale = np.log(rng.uniform(0.01, 0.05, (n, 3))).astype(np.float32)
    instance = (np.arange(n) % 3).astype(np.int32)
    semantic = instance.copy()
    semantic[:5], instance[:5] = -1, -1
    sh = ((colors - 0.5) / SH_C0)[:, None, :]  # the DC band only
    quats = np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))
    gaussians = GaussianScene(
        means=points, sh=sh, opacity_logits=np.ones(n, np.float32), log_scales=log_scale, quats=quats, fitted=True
    )
    write_gaussian_ply(GAUSSIANS_PLY.path(out), gaussians, np.zeros((n, 3), np.float32), semantic, instance)
    embeddings = np.eye(len(CLASSES), dim, dtype=np.float32)
    rows, feats = [], []
    for k, (name, kind) in enumerate(CLASSES):
        mine = points[instance == k]
        rows.append({"id": k, "class_index": k, "class_name": name, "kind": kind, "score": 0.9,
                     "num_points": len(mine), "centroid": mine.mean(0).tolist(),
                     "bbox_min": mine.min(0).tolist(), "bbox_max": mine.max(0).tolist()})  # fmt: skip
        feats.append(embeddings[k])
    (out / "instances.json").write_text(json.dumps(rows))
    np.save(out / "instance_features.npy", np.asarray(feats, np.float32))
    np.save(out / "vocabulary.npy", embeddings)
    vocabulary = {"classes": [{"name": n, "kind": k} for n, k in CLASSES], "embeddings": "vocabulary.npy",
                  "space": "test-space"}  # fmt: skip
    (out / "vocabulary.json").write_text(json.dumps(vocabulary))
    return {"points": points, "colors": colors, "scale": np.exp(log_scale).mean(1), "semantic": semantic,
            "instance": instance}  # fmt: skip
