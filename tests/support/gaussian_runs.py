"""Hand-made Gaussian scenes for the render tests (core and service)."""

from __future__ import annotations

import math

import numpy as np

from panogs_core.gaussians.config import GaussianScene
from panogs_core.gaussians.spherical_harmonics import SH_C0


def opaque_gaussians(means: np.ndarray, colors: np.ndarray, scale: float) -> GaussianScene:
    """Nearly opaque isotropic Gaussians of ``scale`` metres at ``means`` (N, 3) with RGB ``colors`` (N, 3) in [0, 1]
    (SH degree 0, identity rotations), marked as fitted."""
    n = len(means)
    sh = np.zeros((n, 1, 3), np.float32)
    sh[:, 0] = (np.asarray(colors, np.float32) - 0.5) / SH_C0
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1
    return GaussianScene(
        means=np.asarray(means, np.float32),
        sh=sh,
        opacity_logits=np.full(n, 5.0, np.float32),
        log_scales=np.full((n, 3), math.log(scale), np.float32),
        quats=quats,
        fitted=True,
    )
