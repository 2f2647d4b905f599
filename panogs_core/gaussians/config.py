"""The Gaussian scene of the appearance stage: its settings, its per-device schedule and its checkpoint.

Kept apart from :mod:`panogs_core.gaussians` (the stage's entry point) and :mod:`panogs_core.gaussians.fit` (the
torch optimisation) so that both, and the exporters, import these types without importing each other.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import ConfigError, ShapeError
from panogs_core.io.npz import save_npz

# 1 / (2 sqrt(pi)), the DC band's basis value: here rather than in spherical_harmonics, which imports torch.
SH_C0 = 0.28209479177387814
# Per-device defaults (see the module docstring and docs/benchmarks.md for the measurements behind them).
CPU_ITERATIONS = 220
# The CPU's time budget, as Gaussian-iterations: 4.4M gives the whole 220 iterations up to 20k Gaussians (7-Scenes'
# stride-10 import), 146 at 30k and 56 at the scannet-size room's 79k, whose stage took 13.1 s of CPU (22.8 s wall
# on the shared 2-core machine at load 5; bench/gaussians.py stage --preset scannet-size; docs/benchmarks.md).
CPU_GAUSSIAN_ITERATIONS = 4_400_000
CPU_MIN_ITERATIONS = 10
CPU_FIT_WIDTH = 160  # px
CPU_LR_SCALE = 4.0
# The CPU's coarse to fine: the first 70 % of the iterations at half the width (many views cheaply, then the
# detail; docs/benchmarks.md, "Gaussian scene").
CPU_COARSE_FRACTION = 0.7
GPU_ITERATIONS = 7000
GPU_LR_SCALE = 1.0
# Key frames kept in memory at most (evenly spaced over the capture): the targets are held as uint8 images.
_MAX_FRAMES_DEFAULT = 400


@dataclass(frozen=True, kw_only=True)
class AppearanceConfig:
    """Settings of the appearance fit. Learning rates: 3DGS ``OptimizationParams`` defaults (docs/gaussians.md).

    Raises:
        ConfigError: naming the field, when a value is out of range.
    """

    enabled: bool = True  # False: gaussians.ply keeps the initialisation (``initialisation``), not fitted
    sh_degree: int = 1  # final spherical-harmonics degree, 0..3 (3DGS: 3)
    sh_increase_every: int = 1000  # iterations per SH degree step (3DGS: 1000)
    iterations: int | None = None  # None: CPU_ITERATIONS on the CPU, GPU_ITERATIONS on CUDA
    fit_width: int | None = None  # px, render width during the fit; None: CPU_FIT_WIDTH on the CPU, full on CUDA
    lr_scale: float | None = None  # factor on every learning rate; None: CPU_LR_SCALE / GPU_LR_SCALE
    lr_sh_dc: float = 0.0025  # 3DGS feature_lr
    lr_sh_rest: float = 0.0025 / 20  # 3DGS: feature_lr / 20
    lr_opacity: float = 0.05  # 3DGS opacity_lr (original release)
    lr_scale_log: float = 0.005  # 3DGS scaling_lr
    lr_rotation: float = 0.001  # 3DGS rotation_lr
    lr_position: float = 0.00016  # 3DGS position_lr_init, times the scene extent (camera spread), only when moving
    dssim_weight: float = 0.2  # lambda of L1 + D-SSIM (3DGS)
    # Ours: the photometric term, l1 (3DGS) or l2 (the squared error, which PSNR measures: on the CPU schedule it
    # gained 0.35 dB on 7-Scenes' held-out views and lost 0.43 dB on the synthetic scan room's; docs/benchmarks.md)
    photometric_norm: str = "l1"
    # Ours: this fraction of the iterations (the first ones) renders at half the fit width (coarse to fine); None:
    # CPU_COARSE_FRACTION on the CPU, 0 on CUDA
    coarse_fraction: float | None = None
    # Ours: a Gaussian's scale may grow at most this factor over its initial (neighbour-distance) scale. The centres
    # sit on vertices a few cm apart, so larger Gaussians add nothing the neighbours cannot, and they make every
    # tile's list longer (the CPU fit slowed down 10x in 60 iterations without a cap; docs/benchmarks.md).
    max_scale_growth: float = 4.0
    # Ours: a per-frame gain and bias per colour channel, learned with the Gaussians; off by default, it did not
    # help on the CPU schedule (docs/gaussians.md, "Exposure")
    exposure_compensation: bool = False
    lr_exposure: float = 0.001
    move_centres: bool = False  # reference fix_ply: centres stay on the geometry
    max_centre_offset: float = 0.01  # m, how far a centre may move when move_centres is on
    max_frames: int = _MAX_FRAMES_DEFAULT  # key frames used at most (evenly spaced)
    held_out_every: int = 0  # > 0: frames i % n == 0 are left out of the fit and used for the PSNR (benchmarks)
    # torch intra-op threads during a CPU fit (restored after it); None keeps torch's setting. One thread: the fit's
    # tensors are small (160 x 120 images), and on the shared 2-core machine the stage took 29 s with one thread
    # against 244 s with two (bench/gaussians.py stage --threads 1 / 2; docs/benchmarks.md).
    cpu_threads: int | None = 1
    device: str = "auto"  # auto: CUDA when torch sees it (decided when the stage runs), else cpu
    backend: str = "auto"  # auto | torch | gsplat (backends.resolve_backend)
    seed: int = 0  # frame order
    # surface: flat Gaussians from the local spacing, opacity 0.9, colours from the frames that see them
    # (panogs_core.gaussians.surface_init.py); reference: isotropic at sqrt(0.05) x the spacing, opacity 0.5, the
    # primitives' colours (the reference's initialisation)
    initialisation: str = "surface"

    def __post_init__(self) -> None:
        if not (isinstance(self.sh_degree, int) and 0 <= self.sh_degree <= 3):
            raise ConfigError(f"appearance.sh_degree: expected an integer in [0, 3], got {self.sh_degree!r}")
        for name in ("sh_increase_every", "max_frames"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ConfigError(f"appearance.{name}: expected an integer >= 1, got {value!r}")
        for name in ("iterations", "fit_width", "cpu_threads"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise ConfigError(f"appearance.{name}: expected null or an integer >= 1, got {value!r}")
        if not (isinstance(self.held_out_every, int) and self.held_out_every >= 0):
            raise ConfigError(f"appearance.held_out_every: expected an integer >= 0, got {self.held_out_every!r}")
        rates = {n: getattr(self, n) for n in ("lr_sh_dc", "lr_sh_rest", "lr_opacity", "lr_scale_log")}
        rates |= {"lr_rotation": self.lr_rotation, "lr_position": self.lr_position}
        rates["max_centre_offset"] = self.max_centre_offset
        rates["lr_exposure"] = self.lr_exposure
        rates["max_scale_growth"] = self.max_scale_growth
        if self.lr_scale is not None:
            rates["lr_scale"] = self.lr_scale
        for name, value in rates.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"appearance.{name}: expected a finite value > 0, got {value!r}")
        if self.coarse_fraction is not None and not (0.0 <= self.coarse_fraction <= 1.0):
            raise ConfigError(
                f"appearance.coarse_fraction: expected null or a value in [0, 1], got {self.coarse_fraction!r}"
            )
        if not (0.0 <= self.dssim_weight <= 1.0):
            raise ConfigError(f"appearance.dssim_weight: expected a value in [0, 1], got {self.dssim_weight!r}")
        # Checked by form, not with torch.device: importing the config must not import torch (API process).
        if re.fullmatch(r"auto|cpu|cuda(:\d+)?", self.device) is None:
            raise ConfigError(f"appearance.device: expected auto, cpu or cuda[:N], got {self.device!r}")
        if self.initialisation not in ("surface", "reference"):
            raise ConfigError(f"appearance.initialisation: expected surface or reference, got {self.initialisation!r}")
        if self.photometric_norm not in ("l1", "l2"):
            raise ConfigError(f"appearance.photometric_norm: expected l1 or l2, got {self.photometric_norm!r}")
        if self.backend not in ("auto", "torch", "gsplat"):
            raise ConfigError(f"appearance.backend: expected auto, torch or gsplat, got {self.backend!r}")


@dataclass(frozen=True)
class GaussianScene:
    """The scene's Gaussians in the 3DGS parameterisation, after (or without) the appearance fit."""

    means: np.ndarray  # (N, 3) float32, world metres
    sh: np.ndarray  # (N, (sh_degree + 1)^2, 3) float32, SH coefficients (DC first)
    opacity_logits: np.ndarray  # (N,) float32
    log_scales: np.ndarray  # (N, 3) float32
    quats: np.ndarray  # (N, 4) float32 (w, x, y, z), unit
    fitted: bool  # False: the initialisation (stage off, or no colour frame)
    iterations: int = 0
    psnr_before: float | None = None  # dB, mean over the evaluation frames at the fit resolution
    psnr_after: float | None = None
    ssim_before: float | None = None
    ssim_after: float | None = None
    evaluated_on: str = ""  # "held-out" | "training" | ""
    skipped_frames: tuple[str, ...] = ()  # key frames without colour
    note: str = ""
    extra: dict[str, Any] = field(default_factory=dict)  # timings etc. (not checkpointed)

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {"means": (n, 3), "opacity_logits": (n,), "log_scales": (n, 3), "quats": (n, 4)}
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise ShapeError(f"GaussianScene.{name}: expected shape {shape}, got {got}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ShapeError(f"GaussianScene.sh: expected shape ({n}, K, 3), got {self.sh.shape}")

    @property
    def sh_degree(self) -> int:
        return math.isqrt(self.sh.shape[1]) - 1

    def dc_colors(self) -> np.ndarray:  # (N, 3) float32 in [0, 1]
        """Each Gaussian's colour without its view dependence (the DC band alone), as 3DGS converts it."""
        return np.clip(0.5 + SH_C0 * self.sh[:, 0, :], 0.0, 1.0).astype(np.float32)

    def summary(self) -> dict[str, Any]:
        """The report.json fields of the stage."""
        return {
            "fitted": self.fitted,
            "iterations": self.iterations,
            "sh_degree": self.sh_degree,
            "psnr_before": _rounded(self.psnr_before),
            "psnr_after": _rounded(self.psnr_after),
            "ssim_before": _rounded(self.ssim_before),
            "ssim_after": _rounded(self.ssim_after),
            "evaluated_on": self.evaluated_on,
            "frames_without_color": list(self.skipped_frames),
            "note": self.note,
        }

    def save(self, path: str | Path) -> None:
        """One ``.npz`` at exactly ``path`` (no pickles)."""
        scalars = {k: v for k, v in self.summary().items() if k not in ("sh_degree",)}
        save_npz(
            path,
            means=self.means,
            sh=self.sh,
            opacity_logits=self.opacity_logits,
            log_scales=self.log_scales,
            quats=self.quats,
            summary=np.array(json.dumps(scalars)),
        )

    @classmethod
    def load(cls, path: str | Path) -> GaussianScene:
        """Read what :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as z:
            s = json.loads(str(z["summary"]))
            return cls(
                means=z["means"],
                sh=z["sh"],
                opacity_logits=z["opacity_logits"],
                log_scales=z["log_scales"],
                quats=z["quats"],
                fitted=bool(s["fitted"]),
                iterations=int(s["iterations"]),
                psnr_before=s["psnr_before"],
                psnr_after=s["psnr_after"],
                ssim_before=s["ssim_before"],
                ssim_after=s["ssim_after"],
                evaluated_on=str(s["evaluated_on"]),
                skipped_frames=tuple(s["frames_without_color"]),
                note=str(s["note"]),
            )


def initial_gaussians(prims: Any, colors: np.ndarray, sh_degree: int = 0, note: str = "") -> GaussianScene:
    """The primitives' initialisation as a :class:`GaussianScene`: DC colour, identity rotations, no fit."""
    n = prims.points.shape[0]
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3), np.float32)
    sh[:, 0, :] = (np.asarray(colors, np.float32) - 0.5) / SH_C0
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1.0
    return GaussianScene(
        means=np.asarray(prims.points, np.float32),
        sh=sh,
        opacity_logits=np.asarray(prims.opacities, np.float32),
        log_scales=np.asarray(prims.scales, np.float32),
        quats=quats,
        fitted=False,
        note=note,
    )


@dataclass(frozen=True)
class Schedule:
    iterations: int
    fit_width: int
    lr_scale: float
    device: str
    coarse_fraction: float = 0.0


def resolve_schedule(
    cfg: AppearanceConfig, camera_width: int, cuda: bool, num_gaussians: int | None = None
) -> Schedule:
    """The iterations, fit width, learning-rate factor and device of a run (the per-device defaults).

    On the CPU the default iterations shrink with the number of Gaussians to fit the time budget
    (``CPU_GAUSSIAN_ITERATIONS``); iterations set in the config are kept as they are.

    Raises:
        ConfigError: a CUDA device was asked for where torch sees none.
    """
    device = cfg.device if cfg.device != "auto" else ("cuda" if cuda else "cpu")
    if device.startswith("cuda") and not cuda:
        raise ConfigError(f"appearance.device: {cfg.device!r} asked for, but torch sees no CUDA device here")
    on_gpu = device.startswith("cuda")
    iterations = cfg.iterations or (GPU_ITERATIONS if on_gpu else CPU_ITERATIONS)
    if not cfg.iterations and not on_gpu and num_gaussians:
        budget = CPU_GAUSSIAN_ITERATIONS // num_gaussians
        iterations = min(iterations, max(CPU_MIN_ITERATIONS, budget))
    width = cfg.fit_width or (camera_width if on_gpu else CPU_FIT_WIDTH)
    lr_scale = cfg.lr_scale or (GPU_LR_SCALE if on_gpu else CPU_LR_SCALE)
    return Schedule(
        iterations=iterations,
        fit_width=min(width, camera_width),
        lr_scale=lr_scale,
        device=device,
        coarse_fraction=(0.0 if on_gpu else CPU_COARSE_FRACTION)
        if cfg.coarse_fraction is None
        else cfg.coarse_fraction,
    )


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(float(value), 4)
