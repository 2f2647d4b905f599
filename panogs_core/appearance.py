"""Stage 1b: fit the Gaussians' appearance (SH colour, opacity, scale, rotation) to the key frames' colour images.

PanoGS reference section 2 (``run_recon.py`` with ``fix_ply``): the Gaussians start at the geometry's vertices
(:mod:`panogs_core.primitives`) and 3D Gaussian splatting optimises their appearance against the RGB frames with
the L1 + D-SSIM loss, centres fixed. Here:

* one key frame per iteration (a shuffled pass over the frames, then the next pass), rendered at ``fit_width``
  (the camera scaled, same field of view) by :func:`panogs_core.splat_backends.render`: gsplat on a CUDA device,
  the pure-torch rasteriser elsewhere;
* Adam with one learning rate per parameter group, the 3DGS values (docs/gaussians.md), times ``lr_scale``;
* the SH degree grows by one every ``sh_increase_every`` iterations up to ``sh_degree`` (as 3DGS does);
* centres fixed by default; ``move_centres`` lets each move within ``max_centre_offset`` metres of its vertex;
* frames without colour are skipped (listed in the result, for report.json); a bundle without any colour frame
  returns the initialisation unchanged, with a note saying why.

DEPARTURE (schedule): 3DGS trains 30k iterations at full resolution on a GPU. The default schedule is per device
(``iterations`` / ``fit_width`` None): on the CPU a short one at a low resolution with larger learning rates, sized
to a time budget measured on the small demo room (docs/benchmarks.md, ``bench/gaussians.py``); on a GPU a longer
one at the camera's resolution.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.bundle import Scene
from panogs_core.errors import ConfigError, ShapeError
from panogs_core.progress import ProgressFn
from panogs_core.types import Frame

log = logging.getLogger(__name__)

# Per-device defaults (see the module docstring and docs/benchmarks.md for the measurements behind them).
CPU_ITERATIONS = 120
CPU_FIT_WIDTH = 160  # px
CPU_LR_SCALE = 4.0
GPU_ITERATIONS = 7000
GPU_LR_SCALE = 1.0
# Key frames kept in memory at most (evenly spaced over the capture): the targets are held as uint8 images.
_MAX_FRAMES_DEFAULT = 400
# At most this many frames are rendered to measure PSNR before and after the fit (evenly spaced).
_EVAL_FRAMES = 8


@dataclass(frozen=True, kw_only=True)
class AppearanceConfig:
    """Settings of the appearance fit. Learning rates: 3DGS ``OptimizationParams`` defaults (docs/gaussians.md).

    Raises:
        ConfigError: naming the field, when a value is out of range.
    """

    enabled: bool = True  # False: gaussians.ply keeps the initialisation (vertex colour, opacity 0.5, isotropic)
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
    # Ours: a Gaussian's scale may grow at most this factor over its initial (neighbour-distance) scale. The centres
    # sit on vertices a few cm apart, so larger Gaussians add nothing the neighbours cannot, and they make every
    # tile's list longer (the CPU fit slowed down 10x in 60 iterations without a cap; docs/benchmarks.md).
    max_scale_growth: float = 4.0
    move_centres: bool = False  # reference fix_ply: centres stay on the geometry
    max_centre_offset: float = 0.01  # m, how far a centre may move when move_centres is on
    max_frames: int = _MAX_FRAMES_DEFAULT  # key frames used at most (evenly spaced)
    held_out_every: int = 0  # > 0: frames i % n == 0 are left out of the fit and used for the PSNR (benchmarks)
    # torch intra-op threads during a CPU fit (restored after it); None keeps torch's setting. One thread: the fit's
    # tensors are small (160 x 120 images), and on the shared 2-core machine the stage took 29 s with one thread
    # against 244 s with two (bench/gaussians.py stage --threads 1 / 2; docs/benchmarks.md).
    cpu_threads: int | None = 1
    device: str = "auto"  # auto: CUDA when torch sees it (decided when the stage runs), else cpu
    backend: str = "auto"  # auto | torch | gsplat (splat_backends.resolve_backend)
    seed: int = 0  # frame order

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
        rates["max_scale_growth"] = self.max_scale_growth
        if self.lr_scale is not None:
            rates["lr_scale"] = self.lr_scale
        for name, value in rates.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"appearance.{name}: expected a finite value > 0, got {value!r}")
        if not (0.0 <= self.dssim_weight <= 1.0):
            raise ConfigError(f"appearance.dssim_weight: expected a value in [0, 1], got {self.dssim_weight!r}")
        # Checked by form, not with torch.device: importing the config must not import torch (API process).
        if re.fullmatch(r"auto|cpu|cuda(:\d+)?", self.device) is None:
            raise ConfigError(f"appearance.device: expected auto, cpu or cuda[:N], got {self.device!r}")
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
        with open(path, "wb") as fh:
            np.savez(
                fh,
                means=self.means,
                sh=self.sh,
                opacity_logits=self.opacity_logits,
                log_scales=self.log_scales,
                quats=self.quats,
                summary=np.array(_json_dumps(scalars)),
            )

    @classmethod
    def load(cls, path: str | Path) -> GaussianScene:
        """Read what :meth:`save` wrote."""
        import json

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
    from panogs_core.spherical_harmonics import SH_C0

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
class _Schedule:
    iterations: int
    fit_width: int
    lr_scale: float
    device: str


def resolve_schedule(cfg: AppearanceConfig, camera_width: int, cuda: bool) -> _Schedule:
    """The iterations, fit width, learning-rate factor and device of a run (the per-device defaults).

    Raises:
        ConfigError: a CUDA device was asked for where torch sees none.
    """
    device = cfg.device if cfg.device != "auto" else ("cuda" if cuda else "cpu")
    if device.startswith("cuda") and not cuda:
        raise ConfigError(f"appearance.device: {cfg.device!r} asked for, but torch sees no CUDA device here")
    on_gpu = device.startswith("cuda")
    iterations = cfg.iterations or (GPU_ITERATIONS if on_gpu else CPU_ITERATIONS)
    width = cfg.fit_width or (camera_width if on_gpu else CPU_FIT_WIDTH)
    lr_scale = cfg.lr_scale or (GPU_LR_SCALE if on_gpu else CPU_LR_SCALE)
    return _Schedule(iterations=iterations, fit_width=min(width, camera_width), lr_scale=lr_scale, device=device)


def split_frames(scene: Scene, cfg: AppearanceConfig) -> tuple[list[Frame], list[Frame], list[str]]:
    """(fit frames, held-out frames, ids of frames without colour); only frames with a finite pose count.

    Held out: the frames at positions ``i % held_out_every == 0`` among the colour frames (as 3DGS holds out
    every 8th view). The fit frames are thinned evenly to ``max_frames``.
    """
    posed = [f for f in scene.frames if np.all(np.isfinite(f.T_world_cam))]
    no_color = [f.id for f in posed if f.color is None]
    colored = [f for f in posed if f.color is not None]
    k = cfg.held_out_every
    held = [f for i, f in enumerate(colored) if k > 0 and i % k == 0]
    fit = [f for i, f in enumerate(colored) if not (k > 0 and i % k == 0)]
    if len(fit) > cfg.max_frames:
        picks = np.unique(np.linspace(0, len(fit) - 1, cfg.max_frames).round().astype(int))
        fit = [fit[i] for i in picks]
    return fit, held, no_color


def fit_appearance(
    scene: Scene,
    prims: Any,
    colors: np.ndarray,  # (N, 3) float32 in [0, 1], the initial colours
    cfg: AppearanceConfig,
    *,
    on_progress: ProgressFn | None = None,
) -> GaussianScene:
    """Optimise the Gaussians' appearance against the key frames' colour (module docstring).

    Args:
        scene: The opened bundle (camera, poses, colour images).
        prims: The primitives (centres, log scales, opacity logits).
        colors: Initial colours (the geometry's, else fused, else grey).
        cfg: Stage settings.
        on_progress: ``(iteration, iterations)``; may raise ``Cancelled``.

    Returns:
        The fitted scene; the initialisation with a note when the stage is off or no frame has colour.
    """
    import torch

    fit_frames, held, no_color = split_frames(scene, cfg)
    if not cfg.enabled:
        return initial_gaussians(prims, colors, note="appearance fitting is turned off (appearance.enabled: false)")
    if not fit_frames:
        note = (
            f"appearance fitting skipped: none of the {len(scene.frames)} frames has a colour image"
            if not held
            else "appearance fitting skipped: every colour frame is held out"
        )
        log.warning("%s", note)
        return _with(initial_gaussians(prims, colors, note=note), skipped_frames=tuple(no_color))
    if no_color:
        log.info("appearance: %d frame(s) without colour skipped", len(no_color))
    schedule = resolve_schedule(cfg, scene.camera.width, torch.cuda.is_available())
    from panogs_core.appearance_fit import Fitter

    threads = torch.get_num_threads()
    if cfg.cpu_threads is not None and schedule.device == "cpu":
        torch.set_num_threads(cfg.cpu_threads)
    try:
        fitter = Fitter(scene, prims, colors, cfg, schedule)
        eval_frames = held or _evenly(fit_frames, _EVAL_FRAMES)
        before = fitter.evaluate(eval_frames)
        fitter.train(fit_frames, on_progress)
        after = fitter.evaluate(eval_frames)
    finally:
        torch.set_num_threads(threads)
    note = f"{len(no_color)} frame(s) without colour skipped" if no_color else ""
    log.info(
        "appearance: %d iterations at %d px wide on %s, PSNR %.2f -> %.2f dB (%s)",
        schedule.iterations,
        schedule.fit_width,
        schedule.device,
        before[0],
        after[0],
        "held-out" if held else "training frames",
    )
    seconds = fitter.seconds_per_iteration
    return _with(
        fitter.result(),
        extra={"seconds_per_iteration": float(np.mean(seconds)) if seconds else 0.0, "fit_size": fitter.size},
        iterations=schedule.iterations,
        psnr_before=before[0],
        psnr_after=after[0],
        ssim_before=before[1],
        ssim_after=after[1],
        evaluated_on="held-out" if held else "training",
        skipped_frames=tuple(no_color),
        note=note,
    )


def _evenly(frames: list[Frame], count: int) -> list[Frame]:
    picks = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
    return [frames[i] for i in picks]


def _with(scene: GaussianScene, **changes: Any) -> GaussianScene:
    import dataclasses

    return dataclasses.replace(scene, **changes)


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(float(value), 4)


def _json_dumps(obj: Any) -> str:
    import json

    return json.dumps(obj)
