"""The torch half's frame step: both models loaded once, then one frame's mask and feature maps at a time."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panogs_core.stages.maps2d.config import Maps2DConfig
from panogs_core.stages.maps2d.features import frame_features
from panogs_core.stages.maps2d.masks import automatic_masks
from panogs_core.stages.maps2d.models import LoadedModel, load_clip, load_sam, pick_device
from panogs_core.threads import torch_threads


@dataclass(frozen=True)
class Models:
    """The stage's models, loaded: either may be absent (a masks-only or features-only run)."""

    sam: LoadedModel | None
    clip: LoadedModel | None

    @property
    def feature_dim(self) -> int | None:
        """D of the feature maps (the CLIP projection's width), None without a features model."""
        return int(self.clip.model.config.projection_dim) if self.clip else None

    @property
    def device(self) -> str:
        """The device the stage runs on, as report.json names it (``cpu``, ``cuda:0``)."""
        loaded = self.sam or self.clip
        return str(loaded.device) if loaded else "cpu"


@dataclass(frozen=True)
class ComputedMaps:
    """One frame's computed maps: either may be None when its model did not run."""

    masks: np.ndarray | None  # (Hm, Wm) uint16
    features: np.ndarray | None  # (Hf, Wf, D) float16
    mask_count: int


def load_models(masks_dir: Path | None, features_dir: Path | None, cfg: Maps2DConfig) -> Models:
    """Load both models on the configured device (each once per run)."""
    return Models(
        load_sam(masks_dir, cfg.device, cfg.cpu_precision) if masks_dir is not None else None,
        load_clip(features_dir, cfg.device, cfg.cpu_precision) if features_dir is not None else None,
    )


@contextlib.contextmanager
def threads(cfg: Maps2DConfig) -> Iterator[None]:
    """torch's intra-op threads for the stage on a CPU (``cpu_threads``); nothing on a GPU."""
    device, _ = pick_device(cfg.device)
    with torch_threads(cfg.cpu_threads if device.type == "cpu" else None):
        yield


def process_frame(models: Models, color: np.ndarray, masks: np.ndarray | None, cfg: Maps2DConfig) -> ComputedMaps:
    """The maps of one frame: masks from the SAM model when loaded (else the frame's own), then features."""
    computed = automatic_masks(models.sam, color, cfg) if models.sam is not None else None
    ids = computed if computed is not None else _consecutive(masks)
    features = frame_features(models.clip, color, ids, cfg) if models.clip is not None else None
    return ComputedMaps(computed, features, int(ids.max()) if ids.size else 0)


def _consecutive(masks: np.ndarray | None) -> np.ndarray:
    """A frame's own id map with its ids renumbered 1..K in increasing order (0 stays 0): a bundle's ids may be
    sparse (8-bit maps saturate at 255), and the features are tabled per id."""
    if masks is None:  # the entry checks that a features-only frame brings masks
        raise ValueError("a features-only frame needs its own masks")
    values, inverse = np.unique(masks, return_inverse=True)
    inverse = inverse.reshape(masks.shape)
    return (inverse + (0 if values[0] == 0 else 1)).astype(np.int64)
