"""Stage 1b: fit the Gaussians' appearance (SH colour, opacity, scale, rotation) to the key frames' colour images.

docs/method.md §2 (the reference's ``run_recon.py`` with ``fix_ply``): the Gaussians start at the geometry's vertices
(:mod:`panogs_core.stages.primitives`) and 3D Gaussian splatting optimises their appearance against the RGB frames with
the L1 + D-SSIM loss, centres fixed. Here:

* one key frame per iteration (a shuffled pass over the frames, then the next pass), rendered at ``fit_width``
  (the camera scaled, same field of view) by :func:`panogs_core.gaussians.backends.render`: gsplat on a CUDA device,
  the pure-torch rasteriser elsewhere;
* Adam with one learning rate per parameter group, the 3DGS values (docs/gaussians.md), times ``lr_scale``;
* the SH degree grows by one every ``sh_increase_every`` iterations up to ``sh_degree`` (as 3DGS does);
* centres fixed by default; ``move_centres`` lets each move within ``max_centre_offset`` metres of its vertex;
* frames without colour are skipped (listed in the result, for report.json); a bundle without any colour frame
  returns the initialisation unchanged, with a note saying why;
* given a :class:`~panogs_core.snapshots.StageSnapshot`, the fit saves its state periodically and when
  cancelled, and a fit that finds a snapshot continues from it to the same result.

DEPARTURE (schedule, docs/method.md §2 and docs/gaussians.md): per device and far shorter than 3DGS's: on the CPU
a few iterations at a low resolution with larger learning rates, on a GPU more at the camera's resolution.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from panogs_core.gaussians.config import (
    AppearanceConfig,
    GaussianScene,
    Schedule,
    initial_gaussians,
    resolve_schedule,
)
from panogs_core.io.bundle import Bundle
from panogs_core.progress import ProgressFn
from panogs_core.snapshots import StageSnapshot
from panogs_core.threads import torch_threads
from panogs_core.types import Frame

log = logging.getLogger(__name__)

# At most this many frames are rendered to measure PSNR before and after the fit (evenly spaced).
_EVAL_FRAMES = 8
__all__ = [
    "AppearanceConfig",
    "GaussianScene",
    "Schedule",
    "fit_appearance",
    "initial_gaussians",
    "initialise",
    "resolve_schedule",
    "split_frames",
]


def split_frames(bundle: Bundle, cfg: AppearanceConfig) -> tuple[list[Frame], list[Frame], list[str]]:
    """(fit frames, held-out frames, ids of frames without colour); only frames with a finite pose count.

    Held out: the frames at positions ``i % held_out_every == 0`` among the colour frames (as 3DGS holds out
    every 8th view). The fit frames are thinned evenly to ``max_frames``.
    """
    posed = [f for f in bundle.frames if np.all(np.isfinite(f.T_world_cam))]
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
    bundle: Bundle,
    prims: Any,
    colors: np.ndarray,  # (N, 3) float32 in [0, 1], the initial colours
    cfg: AppearanceConfig,
    *,
    on_progress: ProgressFn | None = None,
    snapshot: StageSnapshot | None = None,
) -> GaussianScene:
    """Optimise the Gaussians' appearance against the key frames' colour (module docstring).

    Args:
        bundle: The opened bundle (camera, poses, colour images).
        prims: The primitives (centres, log scales, opacity logits).
        colors: Initial colours (the geometry's, else fused, else grey).
        cfg: Stage settings.
        on_progress: ``(iteration, iterations)``; may raise ``Cancelled``.
        snapshot: Where the fit keeps its partial state (module docstring); None keeps none.

    Returns:
        The fitted scene; the initialisation with a note when the stage is off or no frame has colour (when it is
        off, the primitives' own: the surface initialisation reads every fit frame's colour for a start that no fit
        uses, and an unfitted scene is written from the primitives anyway, ``export.write_gaussians``).
    """
    import torch

    if not cfg.enabled:
        return _with(
            initial_gaussians(prims, colors), note="appearance fitting is turned off (appearance.enabled: false)"
        )
    fit_frames, held, no_color = split_frames(bundle, cfg)
    start = initialise(bundle, prims, colors, fit_frames, cfg)
    if not fit_frames:
        note = (
            f"appearance fitting skipped: none of the {len(bundle.frames)} frames has a colour image"
            if not held
            else "appearance fitting skipped: every colour frame is held out"
        )
        log.warning("%s", note)
        return _with(start, note=note, skipped_frames=tuple(no_color))
    if no_color:
        log.info("appearance: %d frame(s) without colour skipped", len(no_color))
    schedule = resolve_schedule(cfg, bundle.camera.width, torch.cuda.is_available(), len(prims.points))
    from panogs_core.gaussians.fit import Fitter

    with torch_threads(cfg.cpu_threads if schedule.device == "cpu" else None):
        fitter = Fitter(bundle, start, cfg, schedule)
        eval_frames = held or _evenly(fit_frames, _EVAL_FRAMES)
        saved = snapshot.load() if snapshot is not None else None
        if saved is not None and fitter.restore(saved):
            log.info("appearance: resuming the fit at iteration %d of %d", fitter.iteration, schedule.iterations)
        if fitter.scores_before is None:
            fitter.scores_before = fitter.evaluate(eval_frames)
        before = fitter.scores_before
        fitter.train(fit_frames, on_progress, snapshot)
        after = fitter.evaluate(eval_frames)
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


def initialise(
    bundle: Bundle, prims: Any, colors: np.ndarray, frames: list[Frame], cfg: AppearanceConfig
) -> GaussianScene:
    """The fit's starting point (``cfg.initialisation``): ``surface`` (:mod:`panogs_core.gaussians.surface_init`:
    flat Gaussians from the local spacing, opacity 0.9, colours from the fit frames) or ``reference`` (the
    primitives' isotropic scales, opacity 0.5, the given colours)."""
    start = initial_gaussians(prims, colors)
    if cfg.initialisation == "reference":
        return start
    from panogs_core.gaussians.surface_init import SurfaceInit, frame_colors, surface_shapes

    init = SurfaceInit()
    log_scales, quats = surface_shapes(start.means, init)
    rgb = np.asarray(colors, np.float32)
    if frames:
        rgb, _ = frame_colors(bundle, frames, start.means, rgb, init)
    logit = float(np.log(init.opacity / (1.0 - init.opacity)))
    return _with(
        initial_gaussians(prims, rgb),
        log_scales=log_scales,
        quats=quats,
        opacity_logits=np.full(len(start.means), logit, np.float32),
    )


def _evenly(frames: list[Frame], count: int) -> list[Frame]:
    picks = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
    return [frames[i] for i in picks]


def _with(scene: GaussianScene, **changes: Any) -> GaussianScene:
    import dataclasses

    return dataclasses.replace(scene, **changes)
