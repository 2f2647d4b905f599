"""The optimisation behind :func:`panogs_core.gaussians.fit_appearance` (torch; imported only when it runs)."""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import torch

from panogs_core.errors import Cancelled
from panogs_core.gaussians.backends import Backend, render
from panogs_core.gaussians.photometric import photometric_loss, psnr, ssim
from panogs_core.gaussians.rasterizer import Gaussians3D, PinholeCamera
from panogs_core.gaussians.spherical_harmonics import num_coefficients, sh_to_color
from panogs_core.io.bundle import Bundle
from panogs_core.progress import ProgressFn, report
from panogs_core.snapshots import SNAPSHOT_EVERY_S, StageSnapshot
from panogs_core.types import Frame

if TYPE_CHECKING:
    from panogs_core.gaussians.config import AppearanceConfig, GaussianScene, Schedule

ADAM_EPS = 1e-15  # 3DGS: tiny epsilon, so that small gradients of rarely seen Gaussians still move them


class Fitter:
    """Parameters, optimiser and target images of one appearance fit."""

    def __init__(self, bundle: Bundle, init: GaussianScene, cfg: AppearanceConfig, schedule: Schedule) -> None:
        self.bundle = bundle
        self.cfg = cfg
        self.schedule = schedule
        self.device = torch.device(schedule.device)
        dev = self.device
        n = init.means.shape[0]
        height = max(1, round(bundle.camera.height * schedule.fit_width / bundle.camera.width))
        self.size = (schedule.fit_width, height)  # the size of the scores and the exported renders
        coarse = max(1, schedule.fit_width // 2)
        self.coarse_size = (coarse, max(1, round(bundle.camera.height * coarse / bundle.camera.width)))
        self.anchor = torch.as_tensor(init.means, device=dev)
        sh = torch.zeros(n, num_coefficients(cfg.sh_degree), 3, device=dev)
        sh[:, 0] = torch.as_tensor(init.sh[:, 0], device=dev)
        self.sh_dc = sh[:, :1].clone().requires_grad_(True)
        self.sh_rest = sh[:, 1:].clone().requires_grad_(True)
        self.opacity = torch.as_tensor(init.opacity_logits, device=dev).clone().requires_grad_()
        self.log_scales = torch.as_tensor(init.log_scales, device=dev).clone().requires_grad_()
        self.max_log_scales = self.log_scales.detach() + float(np.log(cfg.max_scale_growth))
        self.seconds_per_iteration: list[float] = []
        self.quats = torch.as_tensor(init.quats, device=dev).clone().requires_grad_(True)
        self.offsets = torch.zeros(n, 3, device=dev, requires_grad=cfg.move_centres)
        # Per-frame exposure (an affine map per colour channel: gain 1 + g, bias b) of the training frames, so that
        # the Gaussians do not chase each frame's exposure; renders for evaluation and export use none.
        self.frame_index = {f.id: i for i, f in enumerate(bundle.frames)}
        self.exposure = torch.zeros(len(bundle.frames), 2, 3, device=dev, requires_grad=cfg.exposure_compensation)
        s = schedule.lr_scale
        groups = [
            {"params": [self.sh_dc], "lr": cfg.lr_sh_dc * s},
            {"params": [self.sh_rest], "lr": cfg.lr_sh_rest * s},
            {"params": [self.opacity], "lr": cfg.lr_opacity * s},
            {"params": [self.log_scales], "lr": cfg.lr_scale_log * s},
            {"params": [self.quats], "lr": cfg.lr_rotation * s},
        ]
        if cfg.exposure_compensation:
            groups.append({"params": [self.exposure], "lr": cfg.lr_exposure * s})
        if cfg.move_centres:
            groups.append({"params": [self.offsets], "lr": cfg.lr_position * s * _bundle_extent(bundle)})
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=ADAM_EPS)
        self._targets: dict[tuple[str, tuple[int, int]], torch.Tensor] = {}
        self.backend: Backend = cfg.backend  # type: ignore[assignment]
        # Where the training stands: iterations done, and the shuffled pass over the frames (what is left of it and
        # the generator that draws the next one), so that a snapshot resumes on the same frame sequence.
        self.iteration = 0
        self.rng = np.random.default_rng(cfg.seed)
        self.order: list[int] = []
        self.scores_before: tuple[float, float] | None = None  # (PSNR, SSIM) of the initialisation

    def _parameters(self) -> dict[str, torch.Tensor]:
        return {
            "sh_dc": self.sh_dc,
            "sh_rest": self.sh_rest,
            "opacity": self.opacity,
            "log_scales": self.log_scales,
            "quats": self.quats,
            "offsets": self.offsets,
            "exposure": self.exposure,
        }

    def state(self) -> dict[str, Any]:
        """Everything a resumed fit needs to continue exactly where this one stands (:meth:`restore`)."""
        return {
            "iteration": self.iteration,
            "parameters": {name: t.detach().clone() for name, t in self._parameters().items()},
            "optimizer": self.optimizer.state_dict(),
            "rng": json.dumps(self.rng.bit_generator.state),
            "order": list(self.order),
            "scores_before": list(self.scores_before) if self.scores_before else None,
            "seconds_per_iteration": list(self.seconds_per_iteration),
        }

    def restore(self, state: dict[str, Any]) -> bool:
        """Continue from a :meth:`state`; False (and nothing changed) when it does not fit these parameters."""
        saved = state["parameters"]
        params = self._parameters()
        if set(saved) != set(params) or any(saved[k].shape != p.shape for k, p in params.items()):
            return False
        if not 0 <= int(state["iteration"]) <= self.schedule.iterations:
            return False
        with torch.no_grad():
            for name, param in params.items():
                param.copy_(saved[name].to(param.device))
        self.optimizer.load_state_dict(state["optimizer"])
        self.iteration = int(state["iteration"])
        self.rng.bit_generator.state = json.loads(state["rng"])
        self.order = [int(i) for i in state["order"]]
        before = state["scores_before"]
        self.scores_before = (float(before[0]), float(before[1])) if before else None
        self.seconds_per_iteration = [float(x) for x in state["seconds_per_iteration"]]
        return True

    def camera(self, frame: Frame, size: tuple[int, int] | None = None) -> PinholeCamera:
        """The frame's camera at ``size`` (width, height; default the fit's size)."""
        pose = torch.as_tensor(np.asarray(frame.T_world_cam, np.float64))
        return PinholeCamera.from_camera(self.bundle.camera.scaled(*(size or self.size)), pose)

    def target(self, frame: Frame, size: tuple[int, int] | None = None) -> torch.Tensor:  # (H, W, 3) in [0, 1]
        """The frame's colour at ``size`` (default the fit's size; area-averaged), cached as uint8."""
        size = size or self.size
        key = (frame.id, size)
        if key not in self._targets:
            rgb = self.bundle.read_color(frame)
            assert rgb is not None  # split_frames keeps colour frames only
            if (rgb.shape[1], rgb.shape[0]) != size:
                rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
            self._targets[key] = torch.as_tensor(np.ascontiguousarray(rgb), device=self.device)
        return self._targets[key].to(torch.float32) / 255.0

    def gaussians(self) -> Gaussians3D:
        return Gaussians3D(
            means=self.anchor + self.offsets,
            quats=self.quats,
            log_scales=self.log_scales,
            opacity_logits=self.opacity,
        )

    def render(self, frame: Frame, degree: int, size: tuple[int, int] | None = None) -> torch.Tensor:  # (H, W, 3)
        cam = self.camera(frame, size)
        g = self.gaussians()
        centre = cam.T_world_cam[:3, 3].to(dtype=g.means.dtype, device=self.device)
        sh = torch.cat([self.sh_dc, self.sh_rest], dim=1)
        rgb = sh_to_color(sh, g.means, centre, degree)
        # Training differentiates the compositing by hand (rasterizer._CompositeAnalytic), keeping no (pixel,
        # Gaussian) intermediates: autograd through the ops held them all (2,280 MB peak on the large preset's 144k
        # Gaussians at 160 x 120, against 1,659 MB when recomputed) and ran slower.
        # training=True also when scoring (no grad): the training tiles render the same image, faster at these widths
        return render(g, rgb, cam, backend=self.backend, training=True).features

    def train(self, frames: list[Frame], on_progress: ProgressFn | None, snapshot: StageSnapshot | None) -> None:
        """Run the iterations left; ``snapshot`` gets the state every ``SNAPSHOT_EVERY_S`` s and on cancellation."""
        total = self.schedule.iterations
        last_snapshot = time.monotonic()
        while self.iteration < total:
            self._step(frames)
            try:
                report(on_progress, self.iteration, total)
            except Cancelled as stop:
                if snapshot is not None and stop.save_partial_work:
                    snapshot.save(self.state())
                raise
            if snapshot is not None and self.iteration < total and time.monotonic() - last_snapshot > SNAPSHOT_EVERY_S:
                snapshot.save(self.state())
                last_snapshot = time.monotonic()

    def _step(self, frames: list[Frame]) -> None:
        """One iteration: the next frame of the shuffled pass, rendered, scored and stepped."""
        it = self.iteration
        if not self.order:
            self.order = self.rng.permutation(len(frames)).tolist()
        start = time.perf_counter()
        frame = frames[self.order.pop()]
        degree = min(self.cfg.sh_degree, it // self.cfg.sh_increase_every)
        # coarse to fine: the first coarse_fraction of the iterations at half the width
        coarse = it < self.schedule.coarse_fraction * self.schedule.iterations
        size = self.coarse_size if coarse else self.size
        image = self.render(frame, degree, size)
        if self.cfg.exposure_compensation:
            gain_bias = self.exposure[self.frame_index[frame.id]]
            image = image * (1.0 + gain_bias[0]) + gain_bias[1]
        loss = photometric_loss(image, self.target(frame, size), self.cfg.dssim_weight, self.cfg.photometric_norm)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        with torch.no_grad():
            torch.minimum(self.log_scales, self.max_log_scales, out=self.log_scales)
        self.seconds_per_iteration.append(time.perf_counter() - start)
        if self.cfg.move_centres:
            self._clamp_offsets()
        self.iteration = it + 1

    def _clamp_offsets(self) -> None:
        """Project every centre back into the ball of ``max_centre_offset`` around its vertex."""
        with torch.no_grad():
            norm = self.offsets.norm(dim=1, keepdim=True)
            limit = self.cfg.max_centre_offset
            self.offsets.mul_(torch.where(norm > limit, limit / norm.clamp_min(1e-12), torch.ones_like(norm)))

    @torch.no_grad()
    def evaluate(self, frames: list[Frame]) -> tuple[float, float]:
        """Mean PSNR (dB) and SSIM over ``frames`` at the fit size, with the full SH degree."""
        scores = []
        for frame in frames:
            img = self.render(frame, self.cfg.sh_degree).clamp(0, 1)
            target = self.target(frame)
            scores.append((psnr(img, target), float(ssim(img, target))))
        return float(np.mean([s[0] for s in scores])), float(np.mean([s[1] for s in scores]))

    def trained_sh_degree(self) -> int:
        """The highest SH degree any iteration rendered with (the schedule's degree at the last iteration run)."""
        last = max(self.iteration - 1, 0)
        return min(self.cfg.sh_degree, last // self.cfg.sh_increase_every)

    def result(self) -> GaussianScene:
        """The fitted scene, with the SH bands the schedule reached: a band no iteration rendered with got no
        gradient and is all zeros, so it is left out (gaussians.ply then says the degree the colours have)."""
        from panogs_core.gaussians.config import GaussianScene

        with torch.no_grad():
            quats = self.quats / self.quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
            sh = torch.cat([self.sh_dc, self.sh_rest], dim=1)[:, : num_coefficients(self.trained_sh_degree())]
            return GaussianScene(
                means=_np(self.anchor + self.offsets),
                sh=_np(sh),
                opacity_logits=_np(self.opacity),
                log_scales=_np(self.log_scales),
                quats=_np(quats),
                fitted=True,
            )


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float32).numpy().copy()


def _bundle_extent(bundle: Bundle) -> float:
    """3DGS ``spatial_lr_scale``: 1.1 x the largest distance of a camera centre from their mean (m)."""
    centres = np.stack([np.asarray(f.T_world_cam)[:3, 3] for f in bundle.frames])
    return float(1.1 * np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()) or 1.0
