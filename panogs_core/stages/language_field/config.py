"""Settings of the language field (stage 4), apart from :mod:`panogs_core.stages.language_field`.

Both halves of the stage read them: the stage module and its torch half,
:mod:`panogs_core.stages.language_field.triplane`. Here, neither imports the other for them, and importing them
(the API validates job configs) imports no torch.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from panogs_core.errors import ConfigError


@dataclass(frozen=True, kw_only=True)
class LanguageFieldConfig:
    """Settings of the language field (docs/method.md §3.2-3.3; defaults: the reference's ScanNet settings).

    DEPARTURE (training schedule): the reference trains 11 epochs at batch 256 with lr 1e-3 for both groups
    (about 6.4k steps for 150k primitives). On a CPU the cost is per point, not per step, so we make fewer
    passes (4 epochs, batch 1024) with larger learning rates (decoder 5e-3, planes 1e-2). Measured on a
    synthetic 150k-point, 512-d room (ScanNet-20 CLIP embeddings on spatial blobs, 10 % class noise, 2 cores):
    13 s instead of 61 s, decoded argmax agreeing with the fused argmax on 0.901 of the points (reference
    schedule 0.905), mean cosine to the target 0.844 (0.846), accuracy against the true class 0.984 (0.981).
    Larger batches (4096-8192) at the same cost per epoch needed more epochs for the same quality.
    """

    # Metres per tri-plane cell, one per pyramid level (docs/method.md §3.2: ScanNet (0.2, 0.06), Replica (0.1, 0.04)).
    # The Replica levels: at 6 cm a picture 2 cm in front of its wall shares the wall's cells and decodes as
    # wall (picture IoU 0.00 -> 0.95, mIoU 0.871 -> 0.945 on the small default room, seed 0; the full table
    # is in docs/benchmarks.md). The cost is per point, not per cell, so the finer planes cost little.
    cell_sizes: tuple[float, ...] = (0.1, 0.04)
    channels: int = 10  # latent channels C per plane (reference num_components)
    init_scale: float = 0.1  # std of the N(0, s^2) plane initialisation
    hidden_dims: tuple[int, ...] = (128,)  # decoder hidden widths: C -> 128 -> D (ScanNet), no biases
    epochs: int = 4  # passes over the seen primitives (reference: 11)
    # Small scenes get more passes, so every scene trains at least this many steps: at 4 epochs a 7.7k-point
    # scene made only 32 steps and its decoded argmax matched the true class on 0.79 of the points (CLIP
    # space); 16 epochs (128 steps) gave 0.98. 150 steps still lost whole classes on 30k-point rooms (small
    # default preset: every chair decoded as desk on seed 1, mIoU 0.845; 600 steps: 0.951, PRQ(T) 0.77 ->
    # 0.93). Large scenes are unaffected (150k points: 4 epochs are 600 steps).
    min_steps: int = 600
    batch_size: int = 1024  # primitives per step (reference: 256)
    lr: float = 5e-3  # Adam learning rate of the decoder MLP (reference: 1e-3)
    plane_lr: float = 1e-2  # Adam learning rate of the planes (reference: 1e-3, same as the MLP)
    weight_decay: float = 1e-6  # L2 on the decoder weights only (reference)
    betas: tuple[float, float] = (0.9, 0.99)  # Adam betas (reference)
    bound_padding: float = 0.05  # metres added on every side of the primitives' box
    max_resolution: int = 1024  # cap on plane resolution R per level (memory: 3*C*R^2 floats per level)
    # Torch device for training and decoding. The CLI keeps the CPU; a service worker sets "cuda" where it sees a
    # GPU, unless the job names a device (worker/device.py).
    device: str = "cpu"
    seed: int = 0  # seeds plane/decoder initialisation and batch shuffling

    def __post_init__(self) -> None:
        _require(len(self.cell_sizes) >= 1, "cell_sizes", "at least one level", self.cell_sizes)
        for size in self.cell_sizes:
            _require(math.isfinite(size) and size > 0, "cell_sizes", "positive finite metres", self.cell_sizes)
        _require(self.channels >= 1, "channels", ">= 1", self.channels)
        _require(math.isfinite(self.init_scale) and self.init_scale > 0, "init_scale", "> 0", self.init_scale)
        _require(all(h >= 1 for h in self.hidden_dims), "hidden_dims", "widths >= 1", self.hidden_dims)
        _require(self.epochs >= 1, "epochs", ">= 1", self.epochs)
        _require(self.batch_size >= 1, "batch_size", ">= 1", self.batch_size)
        _require(self.min_steps >= 0, "min_steps", ">= 0", self.min_steps)
        _require(math.isfinite(self.lr) and self.lr > 0, "lr", "> 0", self.lr)
        _require(math.isfinite(self.plane_lr) and self.plane_lr > 0, "plane_lr", "> 0", self.plane_lr)
        _require(self.weight_decay >= 0, "weight_decay", ">= 0", self.weight_decay)
        _require(
            len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas),
            "betas",
            "two values in [0, 1)",
            self.betas,
        )
        _require(
            math.isfinite(self.bound_padding) and self.bound_padding >= 0,
            "bound_padding",
            ">= 0",
            self.bound_padding,
        )
        _require(self.max_resolution >= 2, "max_resolution", ">= 2", self.max_resolution)
        # Checked by form, not with torch.device: importing the config must not import torch (API process).
        _require(
            re.fullmatch(r"cpu|cuda(:\d+)?|mps", self.device) is not None,
            "device",
            "cpu, cuda, cuda:N or mps",
            self.device,
        )


def _require(ok: bool, name: str, expected: str, value: object) -> None:
    if not ok:
        raise ConfigError(f"language_field.{name}: expected {expected}, found {value!r}")
