"""The Gaussians' starting point: a surface that already looks like the room before any iteration (numpy only).

* **Shape** from the local point spacing: the ``neighbors`` nearest points' covariance (PCA) gives the surface's
  tangent plane and normal. Each Gaussian's standard deviation along the tangent plane is ``tangent_factor`` x
  the mean distance to its 3 nearest neighbours, so that neighbouring footprints overlap and leave no hole; along
  the normal it is ``normal_factor`` x that where the surface is flat (smallest PCA eigenvalue under
  ``flatness`` x the middle one), the tangential value elsewhere (corners, clutter).
* **Opacity** ``opacity``: one Gaussian over its neighbours' half-overlap covers the background.
* **Colour** from the colour frames that see the centre: each Gaussian is projected into up to ``max_frames``
  frames (evenly spaced), kept where the frame's depth at that pixel agrees within ``depth_tolerance`` (not
  occluded), and its colour is the median of those samples (robust to the frames' exposure changes and motion
  blur); Gaussians no frame sees keep the given colour (vertex colour, else fused, else grey).

The reference's isotropic start leaves black gaps on a real capture that a CPU-budget fit cannot close.
DEPARTURE (initialisation): docs/gaussians.md, "Where panogs departs" and "The initialisation".
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from panogs_core.io.bundle import Bundle
from panogs_core.types import Frame


@dataclass(frozen=True, kw_only=True)
class SurfaceInit:
    neighbors: int = 8  # points in the PCA of the local surface
    tangent_factor: float = 0.7  # std along the surface, x the mean 3-NN distance
    normal_factor: float = 0.15  # std along the normal on flat surfaces, x the same
    flatness: float = 0.1  # flat where the smallest PCA eigenvalue < flatness x the middle one
    opacity: float = 0.9
    max_frames: int = 40  # colour frames sampled for the colours
    sample_width: int = 320  # px, the colour frames are sampled at this width (area-averaged)
    depth_tolerance: float = 0.05  # m, a sample counts when |frame depth - centre depth| is under this (+ 2 %)


def surface_shapes(points: np.ndarray, cfg: SurfaceInit = SurfaceInit()) -> tuple[np.ndarray, np.ndarray]:
    """(log scales (N, 3), unit quaternions (N, 4) w x y z) of Gaussians flat along the local surface.

    The rotation's third column is the normal (smallest eigenvector); scales are (t, t, n).
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    n = len(pts)
    if n < 4:
        log = np.full((n, 3), np.log(0.01), np.float32)
        quats = np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))
        return log, quats
    k = min(cfg.neighbors, n - 1)
    dist, idx = cKDTree(pts).query(pts, k=k + 1)  # column 0: the point itself
    spacing = np.maximum(dist[:, 1:4].mean(axis=1), 1e-4)  # (N,)
    nb = pts[idx] - pts[idx].mean(axis=1, keepdims=True)  # (N, k + 1, 3)
    cov = np.einsum("nki,nkj->nij", nb, nb) / (k + 1)
    evals, evecs = np.linalg.eigh(cov)  # ascending; columns are eigenvectors
    rot = evecs[:, :, [2, 1, 0]]  # tangent (largest), tangent, normal (smallest)
    rot[np.linalg.det(rot) < 0, :, 2] *= -1.0  # proper rotation
    flat = evals[:, 0] < cfg.flatness * np.maximum(evals[:, 1], 1e-18)
    t = cfg.tangent_factor * spacing
    scales = np.stack([t, t, np.where(flat, cfg.normal_factor * spacing, t)], axis=1)
    return np.log(scales).astype(np.float32), _matrix_to_quat(rot).astype(np.float32)


def frame_colors(
    bundle: Bundle,
    frames: Sequence[Frame],
    points: np.ndarray,
    fallback: np.ndarray,
    cfg: SurfaceInit = SurfaceInit(),
) -> tuple[np.ndarray, np.ndarray]:
    """(colours (N, 3) float32 in [0, 1], samples per point (N,)) from the frames that see each point."""
    pts = np.asarray(points, np.float64)
    n = len(pts)
    picks = np.unique(np.linspace(0, len(frames) - 1, min(cfg.max_frames, len(frames))).round().astype(int))
    chosen = [frames[i] for i in picks] if frames else []
    samples = np.full((len(chosen), n, 3), np.nan, np.float32)
    cam0 = bundle.camera
    for j, frame in enumerate(chosen):
        rgb = bundle.read_color(frame)
        if rgb is None:
            continue
        width = min(cfg.sample_width, cam0.width)
        height = max(1, round(cam0.height * width / cam0.width))
        cam = cam0.scaled(width, height)
        rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
        depth = cv2.resize(bundle.read_depth(frame), (width, height), interpolation=cv2.INTER_NEAREST)
        T = np.linalg.inv(np.asarray(frame.T_world_cam, np.float64))
        pc = pts @ T[:3, :3].T + T[:3, 3]
        z = pc[:, 2]
        front = z > 1e-3
        u = np.full(n, -1, np.int64)
        v = np.full(n, -1, np.int64)
        u[front] = np.floor(cam.fx * pc[front, 0] / z[front] + cam.cx).astype(np.int64)
        v[front] = np.floor(cam.fy * pc[front, 1] / z[front] + cam.cy).astype(np.int64)
        inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        ii = np.flatnonzero(inside)
        d = depth[v[ii], u[ii]]
        ok = (d > 0) & (np.abs(d - z[ii]) < cfg.depth_tolerance + 0.02 * z[ii])
        ii = ii[ok]
        samples[j, ii] = rgb[v[ii], u[ii]].astype(np.float32) / 255.0
    count = np.sum(~np.isnan(samples[..., 0]), axis=0) if len(chosen) else np.zeros(n, np.int64)
    colors = np.asarray(fallback, np.float32).copy()
    seen = count > 0
    if seen.any():
        colors[seen] = np.nanmedian(samples[:, seen], axis=0)
    return colors, count


def _matrix_to_quat(rot: np.ndarray) -> np.ndarray:  # (N, 3, 3) proper rotations -> (N, 4) w x y z
    m = rot
    w = np.sqrt(np.maximum(0.0, 1.0 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2])) / 2
    x = np.sqrt(np.maximum(0.0, 1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2])) / 2
    y = np.sqrt(np.maximum(0.0, 1.0 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2])) / 2
    z = np.sqrt(np.maximum(0.0, 1.0 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2])) / 2
    x = np.copysign(x, m[:, 2, 1] - m[:, 1, 2])
    y = np.copysign(y, m[:, 0, 2] - m[:, 2, 0])
    z = np.copysign(z, m[:, 1, 0] - m[:, 0, 1])
    q = np.stack([w, x, y, z], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)
