"""Which rasteriser renders: the pure-torch one (:mod:`panogs_core.gaussians.rasterizer`) or gsplat's CUDA kernels.

gsplat (Apache-2.0, the ``gpu`` extra) compiles its kernels on first use and needs a CUDA device. ``auto`` picks it
when the tensors live on a CUDA device and gsplat imports; everything else uses the torch rasteriser, which is
also the test oracle of the CUDA path (tests/core/test_gsplat_parity.py).

Conventions bridged here: gsplat puts pixel centres at +0.5 (docs/conventions.md puts them at integers), so its
principal point is shifted by +0.5; it takes activated scales and opacities; its expected depth ("ED") is the
blended camera z over the accumulated alpha, as :func:`panogs_core.gaussians.rasterizer.rasterize` returns it.
"""

from __future__ import annotations

import importlib.util
from typing import Literal

import torch

from panogs_core.errors import ConfigError
from panogs_core.gaussians.rasterizer import (
    DILATION,
    NEAR_PLANE,
    Gaussians3D,
    PinholeCamera,
    Render,
    rasterize,
    world_to_camera,
)

Backend = Literal["auto", "torch", "gsplat"]

# The torch rasteriser's (tile_size, tiles_per_batch, chunk) in a training step: 4 x 4 tiles, 64 per batch, 64
# Gaussians per compositing step. A fit step (forward and backward) of 7-Scenes' 20k Gaussians took 0.090 s at
# 80 x 60 and 0.165 s at 160 x 120 against 0.211 / 0.215 s with the renders' 8 x 8 tiles, 64 per batch, chunks of
# 128 (bench/gaussians.py tiles): the low widths of the CPU schedule put many Gaussians in each tile, and every
# pixel of a tile evaluates its whole list.
TRAINING_TILES = (4, 64, 64)


def gsplat_installed() -> bool:
    """True when the ``gpu`` extra (gsplat) is installed; its kernels still need CUDA to build and run."""
    return importlib.util.find_spec("gsplat") is not None


def resolve_backend(backend: Backend, device: torch.device) -> Literal["torch", "gsplat"]:
    """The rasteriser to use for tensors on ``device``.

    Raises:
        ConfigError: ``gsplat`` was asked for without CUDA or without the ``gpu`` extra.
    """
    if backend == "torch":
        return "torch"
    usable = device.type == "cuda" and gsplat_installed()
    if backend == "gsplat" and not usable:
        raise ConfigError(
            f"backend 'gsplat' needs a CUDA device and the gpu extra (pip install 'panogs[gpu]'); "
            f"device is {device}, gsplat installed: {gsplat_installed()}"
        )
    if backend not in ("auto", "gsplat"):
        raise ConfigError(f"backend: expected 'auto', 'torch' or 'gsplat', got {backend!r}")
    return "gsplat" if usable else "torch"


def render(
    gaussians: Gaussians3D,
    features: torch.Tensor,  # (N, C)
    camera: PinholeCamera,
    *,
    backend: Backend = "auto",
    background: torch.Tensor | None = None,
    training: bool = False,
) -> Render:
    """Blend ``features`` for ``camera`` with the chosen rasteriser (``top_index`` is not computed here).

    ``training`` picks the pure-torch rasteriser's hand-written backward (gsplat always has its own) and its
    training tiles (``TRAINING_TILES``).
    """
    if resolve_backend(backend, gaussians.means.device) == "gsplat":
        return rasterize_gsplat(gaussians, features, camera, background=background)
    if training:
        tile_size, tiles_per_batch, chunk = TRAINING_TILES
        return rasterize(
            gaussians,
            features,
            camera,
            background=background,
            analytic_backward=True,
            tile_size=tile_size,
            tiles_per_batch=tiles_per_batch,
            chunk=chunk,
        )
    return rasterize(gaussians, features, camera, background=background)


def rasterize_gsplat(
    gaussians: Gaussians3D,
    features: torch.Tensor,  # (N, C)
    camera: PinholeCamera,
    *,
    background: torch.Tensor | None = None,
) -> Render:
    """The same image formation as :func:`panogs_core.gaussians.rasterizer.rasterize`, through gsplat's CUDA kernels."""
    from gsplat import rasterization

    dev, dtype = gaussians.means.device, gaussians.means.dtype
    view = world_to_camera(camera, dtype, dev)[None]
    intrinsics = torch.tensor(
        [[camera.fx, 0.0, camera.cx + 0.5], [0.0, camera.fy, camera.cy + 0.5], [0.0, 0.0, 1.0]], dtype=dtype, device=dev
    )[None]
    images, alphas, _ = rasterization(
        means=gaussians.means,
        quats=gaussians.quats,
        scales=torch.exp(gaussians.log_scales),
        opacities=torch.sigmoid(gaussians.opacity_logits),
        colors=features,
        viewmats=view,
        Ks=intrinsics,
        width=camera.width,
        height=camera.height,
        near_plane=NEAR_PLANE,
        eps2d=DILATION,
        packed=False,
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    feats, depth = images[0, ..., :-1], images[0, ..., -1]
    alpha = alphas[0, ..., 0]
    if background is not None:
        feats = feats + (1 - alpha)[..., None] * background
    return Render(features=feats, alpha=alpha, depth=depth * (alpha > 0), top_index=None)
