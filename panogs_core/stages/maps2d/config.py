"""Settings of the 2D-maps stage, apart from :mod:`panogs_core.stages.maps2d`.

Both halves of the stage read them: the numpy entry (checkpoint layout, frame loop) and the torch half
(:mod:`panogs_core.stages.maps2d.masks`, :mod:`panogs_core.stages.maps2d.features`). Importing this module (the API
validates job configs) imports no torch. No setting is a path or a model name: the models come from the caller
(the CLI's options, the worker's declared entries), never from a job's config.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from panogs_core.errors import ConfigError

CPU_PRECISIONS = ("auto", "float32", "bfloat16")


@dataclass(frozen=True, kw_only=True)
class Maps2DConfig:
    """Settings of the 2D-maps stage (docs/method.md §17).

    Mask defaults are those of Segment Anything's automatic mask generator, the reference's masks
    (docs/method.md §17); the feature settings are ours (the reference's LSeg has no crops).

    Raises:
        ConfigError: naming the field, when a value is out of range.
    """

    # --- masks (Segment Anything automatic mode) ---
    # Prompt points per image side, a regular grid. None: by device (masks.grid_side), 8 on a CPU (the CPU default,
    # docs/method.md §17: the decoder's cost is linear in the points), 32 (SAM's automatic mode) on a GPU.
    points_per_side: int | None = None
    # prompts per decoder call; memory and speed, not results. None: 4 on a CPU, 64 (SAM's) on a GPU
    # (masks.prompts_per_call; docs/benchmarks.md "2D maps stage costs").
    points_per_batch: int | None = None
    # The model's predicted IoU a mask needs (SAM: 0.88). Scores of random weights sit near 0: tests set <= 0,
    # which keeps every mask.
    pred_iou_thresh: float = 0.88
    stability_score_thresh: float = 0.95  # IoU of the mask at logit +offset vs -offset (SAM: 0.95)
    stability_score_offset: float = 1.0  # logits (SAM: 1.0)
    # DEPARTURE (docs/method.md §17): NMS on the masks' IoU (SAM: on their boxes, 0.7); a box IoU suppresses a
    # part lying inside a larger object's box.
    nms_iou_thresh: float = 0.7
    # ours: fraction of the mask map's pixels a mask needs, before painting (SAM's min_mask_region_area is 0);
    # 5e-4 of 640x480 is 154 pixels, below which a mask rarely holds enough primitives to vote.
    min_mask_fraction: float = 5e-4
    # ours: at most this many candidates (best predicted IoU) enter the NMS; bounds its M x M IoU matrix. SAM has
    # no cap; its filters leave a few hundred on a room's image.
    max_candidates: int = 512
    # ours: at most this many masks per frame, the best predicted IoU first; bounds the crops the feature model
    # embeds (its cost is per crop, docs/benchmarks.md "2D maps stage costs"). Ids fit a 16-bit PNG.
    max_masks: int = 128
    # ours: px, long side of the mask map written (the image is downscaled to it, never upscaled); 640 is the
    # reference's mask size for ScanNet (640x480).
    mask_long_side: int = 640

    # --- language features (mask crops in a CLIP-family image tower) ---
    # ours: cells on the feature map's long side (160 -> 160x120 for 4:3 frames); the map is constant per mask,
    # so it only sets how finely the mask boundaries are drawn.
    feature_long_side: int = 160
    # ours: margin added on each side of a mask's box, as a fraction of its longer side, one crop per value
    # (OpenMask3D crops at growing context; docs/method.md §17). Each crop is a square around the box.
    crop_margins: tuple[float, ...] = (0.1, 0.5)
    # ours: weight of the whole image's embedding blended into a mask's (ConceptFusion blends them); pixels no
    # mask covers always take the whole image's.
    global_mix: float = 0.0
    crops_per_batch: int = 32  # crops per image-tower call; memory, not results

    # --- frames ---
    # ours: maps for every k-th frame with a colour image (1: every frame, the reference's). The stages after this
    # one read the frames without maps as a bundle's non-key frames (depth and pose only), so k divides the
    # stage's time by about k, at the price of the views the masks and features are fused over.
    frame_stride: int = 1

    # --- device ---
    # "auto": the first CUDA device when torch sees one (half precision), else the CPU (float32).
    device: str = "auto"
    # Number format on a CPU (docs/method.md §17, "CPU costs and the CPU default"): "auto" is bfloat16 where the CPU
    # does bfloat16 arithmetic natively (AVX512-BF16 or AMX: 0.6-0.7x the CPU time of float32 and 0.6x the encoder's
    # peak memory, docs/benchmarks.md "2D maps stage costs"), else float32 (emulated bfloat16 is many times
    # slower); "float32" or "bfloat16" force one. A GPU always runs in float16.
    cpu_precision: str = "auto"
    # torch intra-op threads on a CPU (restored after the stage); None keeps torch's setting (the process's
    # thread policy, panogs_core/threads.py).
    cpu_threads: int | None = None

    def __post_init__(self) -> None:
        _require(
            self.points_per_side is None or self.points_per_side >= 1, "points_per_side", "None or >= 1",
            self.points_per_side,
        )  # fmt: skip
        _require(
            self.points_per_batch is None or self.points_per_batch >= 1,
            "points_per_batch",
            "None or >= 1",
            self.points_per_batch,
        )
        _require(_finite_in(self.pred_iou_thresh, -1.0, 1.0), "pred_iou_thresh", "in [-1, 1]", self.pred_iou_thresh)
        _require(
            _finite_in(self.stability_score_thresh, 0.0, 1.0),
            "stability_score_thresh",
            "in [0, 1]",
            self.stability_score_thresh,
        )
        _require(
            math.isfinite(self.stability_score_offset) and self.stability_score_offset >= 0,
            "stability_score_offset",
            ">= 0",
            self.stability_score_offset,
        )
        _require(
            math.isfinite(self.nms_iou_thresh) and 0 < self.nms_iou_thresh <= 1,
            "nms_iou_thresh",
            "in (0, 1]",
            self.nms_iou_thresh,
        )
        _require(_finite_in(self.min_mask_fraction, 0.0, 1.0), "min_mask_fraction", "in [0, 1]", self.min_mask_fraction)
        _require(self.max_candidates >= 1, "max_candidates", ">= 1", self.max_candidates)
        _require(1 <= self.max_masks <= 65535, "max_masks", "in [1, 65535]", self.max_masks)
        _require(self.mask_long_side >= 8, "mask_long_side", ">= 8", self.mask_long_side)
        _require(self.feature_long_side >= 1, "feature_long_side", ">= 1", self.feature_long_side)
        _require(len(self.crop_margins) >= 1, "crop_margins", "at least one margin", self.crop_margins)
        for m in self.crop_margins:
            _require(_finite_in(m, 0.0, 10.0), "crop_margins", "margins in [0, 10]", self.crop_margins)
        _require(_finite_in(self.global_mix, 0.0, 1.0), "global_mix", "in [0, 1]", self.global_mix)
        _require(self.frame_stride >= 1, "frame_stride", ">= 1", self.frame_stride)
        _require(self.crops_per_batch >= 1, "crops_per_batch", ">= 1", self.crops_per_batch)
        # Checked by form, not with torch.device: importing the config must not import torch (API process).
        _require(
            re.fullmatch(r"auto|cpu|cuda(:\d+)?", self.device) is not None,
            "device",
            "auto, cpu, cuda or cuda:N",
            self.device,
        )
        _require(self.cpu_precision in CPU_PRECISIONS, "cpu_precision", " or ".join(CPU_PRECISIONS), self.cpu_precision)
        _require(self.cpu_threads is None or self.cpu_threads >= 1, "cpu_threads", "None or >= 1", self.cpu_threads)

    def mask_settings(self) -> dict[str, object]:
        """The settings the masks depend on (a checkpoint key covers exactly these)."""
        names = (
            "points_per_side",
            "pred_iou_thresh",
            "stability_score_thresh",
            "stability_score_offset",
            "nms_iou_thresh",
            "min_mask_fraction",
            "max_candidates",
            "max_masks",
            "mask_long_side",
            "cpu_precision",
        )
        return {n: getattr(self, n) for n in names}

    def feature_settings(self) -> dict[str, object]:
        """The settings the feature maps depend on, given the masks."""
        return {
            "feature_long_side": self.feature_long_side,
            "crop_margins": list(self.crop_margins),
            "global_mix": self.global_mix,
            "features_cpu_precision": self.cpu_precision,
        }


def scaled_size(height: int, width: int, long_side: int) -> tuple[int, int]:
    """``(h, w)`` of an image scaled so that its long side is at most ``long_side`` (never upscaled), at least 1."""
    scale = min(1.0, long_side / max(height, width))
    return max(1, round(height * scale)), max(1, round(width * scale))


def _finite_in(value: float, lo: float, hi: float) -> bool:
    return math.isfinite(value) and lo <= value <= hi


def _require(ok: bool, name: str, expected: str, value: object) -> None:
    if not ok:
        raise ConfigError(f"maps2d.{name}: expected {expected}, found {value!r}")
