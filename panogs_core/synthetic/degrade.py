"""Sensor degradation of rendered views: depth noise, holes and range limit; colour noise.

Depth model (per pixel, z in metres): ``z + N(0, (sigma_base + sigma_quad * z**2)**2)`` (structured-light and
time-of-flight error grows roughly with z squared), then dropped (0) where: a random fraction of single
pixels; smooth blob-shaped holes covering ``hole_fraction`` of the image (dark, shiny or grazing surfaces);
pixels on depth discontinuities with probability ``edge_dropout`` (mixed pixels at silhouettes); depth beyond
``max_depth_m``.
"""

from __future__ import annotations

import cv2
import numpy as np

from panogs_core.synthetic.presets import DepthNoise

_EDGE_JUMP_M = 0.1  # a depth step larger than this between 4-neighbours marks a silhouette


def smooth_field(shape: tuple[int, int], rng: np.random.Generator, cell: int = 16) -> np.ndarray:  # (H, W)
    """Smooth standard-normal-ish random field with features about ``cell`` pixels across."""
    h, w = shape
    coarse = rng.standard_normal((max(h // cell, 2) + 1, max(w // cell, 2) + 1)).astype(np.float32)
    field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    return (field - field.mean()) / max(float(field.std()), 1e-6)


def blob_mask(shape: tuple[int, int], fraction: float, rng: np.random.Generator, cell: int = 16) -> np.ndarray:
    """Boolean ``(H, W)`` mask of smooth blobs covering about ``fraction`` of the image."""
    if fraction <= 0:
        return np.zeros(shape, dtype=bool)
    field = smooth_field(shape, rng, cell)
    return field > np.quantile(field, 1.0 - fraction)


def depth_edges(depth: np.ndarray) -> np.ndarray:  # (H, W) bool
    """Pixels next to a depth discontinuity (either side)."""
    edge = np.zeros(depth.shape, dtype=bool)
    jump_x = np.abs(np.diff(depth, axis=1)) > _EDGE_JUMP_M
    jump_y = np.abs(np.diff(depth, axis=0)) > _EDGE_JUMP_M
    edge[:, :-1] |= jump_x
    edge[:, 1:] |= jump_x
    edge[:-1, :] |= jump_y
    edge[1:, :] |= jump_y
    return edge


def degrade_depth(depth: np.ndarray, noise: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    """Apply the depth sensor model to a clean depth image.

    Args:
        depth: ``(H, W)`` clean z depth in metres, 0 = no depth.
        noise: Noise, hole and range parameters.
        rng: Source of the noise.

    Returns:
        ``(H, W)`` float32 noisy depth in metres, 0 = no depth.
    """
    valid = depth > 0
    sigma = noise.sigma_base_m + noise.sigma_quad * depth**2
    out = depth + rng.standard_normal(depth.shape).astype(np.float32) * sigma
    drop = rng.random(depth.shape) < noise.dropout
    drop |= blob_mask(depth.shape, noise.hole_fraction, rng, cell=12)
    drop |= depth_edges(depth) & (rng.random(depth.shape) < noise.edge_dropout)
    drop |= depth > noise.max_depth_m
    return np.where(valid & ~drop & (out > 0), out, 0.0).astype(np.float32)


def degrade_color(color: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:  # (H, W, 3) uint8
    """Add Gaussian sensor noise to a ``(H, W, 3)`` float image in [0, 1] and quantise to uint8 RGB."""
    noisy = color + rng.standard_normal(color.shape).astype(np.float32) * sigma
    return np.clip(np.rint(noisy * 255.0), 0, 255).astype(np.uint8)
