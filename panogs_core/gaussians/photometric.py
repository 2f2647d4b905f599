"""Image-quality measures and the photometric loss of the appearance fit.

- SSIM (Wang et al. 2004) with the usual 11 x 11 Gaussian window of standard deviation 1.5 and constants
  ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2`` for images in [0, L = 1], averaged over pixels and channels. The window
  is applied with zero padding ("same" size), as in the 3DGS training code.
- The 3DGS loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` with ``lambda = 0.2`` (Kerbl et al. 2023, section 7.1;
  docs/gaussians.md).
- PSNR for images in [0, 1].
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from panogs_core.errors import ShapeError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
DSSIM_WEIGHT = 0.2  # lambda of the 3DGS loss


def _window(channels: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:  # (C, 1, 11, 11)
    x = torch.arange(SSIM_WINDOW, dtype=dtype, device=device) - SSIM_WINDOW // 2
    g = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images in [0, 1] (a scalar tensor, differentiable)."""
    if a.shape != b.shape or a.ndim != 3:
        raise ShapeError(f"ssim: expected two (H, W, C) images of one shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    c = x.shape[1]
    w = _window(c, x.dtype, x.device)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, w, padding=SSIM_WINDOW // 2, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (num / den).mean()


def photometric_loss(
    render: torch.Tensor, target: torch.Tensor, dssim_weight: float = DSSIM_WEIGHT, norm: str = "l1"
) -> torch.Tensor:
    """``(1 - lambda) |render - target|_1 + lambda (1 - SSIM)`` of (H, W, 3) images (the 3DGS loss); ``norm="l2"``
    takes the mean squared error in place of the L1 term."""
    diff = render - target
    error = diff.abs().mean() if norm == "l1" else (diff * diff).mean()
    if dssim_weight == 0:
        return error
    return (1 - dssim_weight) * error + dssim_weight * (1 - ssim(render, target))


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB of two images in [0, 1] (inf when equal)."""
    mse = float(((a.clamp(0, 1) - b) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
