"""Settings of the language field (stage 4), apart from :mod:`panogs_core.stages.language_field`.

Both halves of the stage read them: the stage module and its torch half,
:mod:`panogs_core.stages.language_field.triplane`. Here, neither imports the other for them, and importing them
(the API validates job configs) imports no torch.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

from panogs_core.errors import ConfigError


@dataclass(frozen=True, kw_only=True)
class LanguageFieldConfig:
    """Settings of the language field (docs/method.md §3.2-3.3; defaults: the reference's ScanNet settings).

    DEPARTURE (schedule, docs/method.md §3.3): 3 epochs (at least 200 steps) at batch 1024 with larger learning
    rates, Adam's second moment at 0.9, the decoder started at the scene's own features and predicting in a 128-d
    basis of them, where the reference trains 11 epochs at batch 256 and lr 1e-3 from PyTorch's init in all D
    dims; on a CPU the cost is per point, not per step. The defaults before 2026-12-05, closer to the reference:
    ``epochs=4, min_steps=600, betas=(0.9, 0.99), basis_dims=None, decoder_init="uniform"`` (about 3x the CPU).
    """

    # Metres per tri-plane cell, one per pyramid level (docs/method.md §3.2: ScanNet (0.2, 0.06), Replica (0.1, 0.04)).
    # DEPARTURE (docs/method.md §3.2): the Replica levels everywhere; at 6 cm a picture decodes as its wall.
    cell_sizes: tuple[float, ...] = (0.1, 0.04)
    channels: int = 10  # latent channels C per plane (reference num_components)
    init_scale: float = 0.1  # std of the N(0, s^2) plane initialisation
    hidden_dims: tuple[int, ...] = (128,)  # decoder hidden widths: C -> 128 -> D (ScanNet), no biases
    # DEPARTURE (docs/method.md §3.3): how the decoder's last layer starts. "targets" makes each of its H columns
    # one of the scene's own unit fused rows (drawn with the seed), at the uniform init's column length, so the
    # decoded features start in the targets' cone and fewer steps fit as closely; "uniform" is PyTorch's default
    # Linear init (the reference).
    decoder_init: Literal["uniform", "targets"] = "targets"
    epochs: int = 3  # passes over the seen primitives (reference: 11; docs/method.md §3.3)
    # DEPARTURE (docs/method.md §3.3): small scenes get more passes, so every scene trains at least this many steps
    # (70k seen points at 3 epochs already make about 200).
    min_steps: int = 200
    batch_size: int = 1024  # primitives per step (reference: 256)
    lr: float = 5e-3  # Adam learning rate of the decoder MLP (reference: 1e-3)
    plane_lr: float = 1e-2  # Adam learning rate of the planes (reference: 1e-3, same as the MLP)
    weight_decay: float = 1e-6  # L2 on the decoder weights only (reference)
    # Adam betas. DEPARTURE (docs/method.md §3.3): the second moment at 0.9 where the reference keeps 0.99: a
    # plane cell is touched by a few batches a pass, and at 0.9 its step follows its recent gradients; at the
    # fewer steps the labels held only with it (docs/benchmarks.md, "Language field speed").
    betas: tuple[float, float] = (0.9, 0.9)
    bound_padding: float = 0.05  # metres added on every side of the primitives' box
    max_resolution: int = 1024  # cap on plane resolution R per level (memory: 3*C*R^2 floats per level)
    # Torch device for training and decoding. The CLI keeps the CPU; a service worker sets "cuda" where it sees a
    # GPU, unless the job names a device (worker/device.py).
    device: str = "cpu"
    # torch intra-op threads during a CPU fit's set-up and steps (restored after it); None keeps torch's setting.
    # One thread: a step's kernels are small (1024 points), and on the shared 2-core machine a lone fit took
    # 100-250 ms a step with two threads (spinning against each other and other processes) against 16-28 ms with
    # one (docs/benchmarks.md). On the AVX2 AMD EPYC: no gain quiet (a reported run), +3-4 % CPU. The set-up's
    # products (the basis, the projection) change in the last bits with the count, so the labels would too. The
    # decoding after the fit takes the run's threads: row by row, the same to the bit at any count
    # (docs/benchmarks.md, "Language field speed").
    cpu_threads: int | None = 1
    # DEPARTURE (docs/method.md §3.3): the decoder predicts in the top `basis_dims` directions of the scene's own
    # fused features and the loss is taken there (the cosine in D dims of a decoder whose outputs lie in that span);
    # None: the full D dims, as the reference. The step's matrix products shrink by D / basis_dims; features of
    # at most `basis_dims` dims train in full. 64 directions cost the ScanNet-size room 1.9 mIoU points; 128 fit
    # as closely as all 512 (docs/benchmarks.md, "Language field speed").
    basis_dims: int | None = 128
    seed: int = 0  # seeds plane/decoder initialisation and batch shuffling

    def __post_init__(self) -> None:
        _require(len(self.cell_sizes) >= 1, "cell_sizes", "at least one level", self.cell_sizes)
        for size in self.cell_sizes:
            _require(math.isfinite(size) and size > 0, "cell_sizes", "positive finite metres", self.cell_sizes)
        _require(self.channels >= 1, "channels", ">= 1", self.channels)
        _require(math.isfinite(self.init_scale) and self.init_scale > 0, "init_scale", "> 0", self.init_scale)
        _require(all(h >= 1 for h in self.hidden_dims), "hidden_dims", "widths >= 1", self.hidden_dims)
        _require(self.decoder_init in ("uniform", "targets"), "decoder_init", "uniform or targets", self.decoder_init)
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
        _require(self.basis_dims is None or self.basis_dims >= 1, "basis_dims", "None or >= 1", self.basis_dims)
        _require(self.cpu_threads is None or self.cpu_threads >= 1, "cpu_threads", "None or >= 1", self.cpu_threads)
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
