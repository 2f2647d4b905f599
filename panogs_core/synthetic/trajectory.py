"""A handheld scanning trajectory: one walk around the room, looking around.

The camera walks a rounded-rectangle loop inset from the walls at 1.3-1.7 m, facing mostly towards the room's
centre with a smooth yaw sweep (so it also looks along and across the walls) and a smooth pitch that keeps the
floor, the furniture and now and then the ceiling in view. Handheld jitter and uneven step lengths come from
:class:`TrajectoryNoise`. Positions too close to tall furniture are pushed towards the centre.
Poses are camera-to-world with OpenCV axes (x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np

from panogs_core.synthetic.layout import NUM_STUFF, Layout
from panogs_core.synthetic.presets import TrajectoryNoise

_HEIGHT = (1.3, 1.7)
_CLEARANCE = 0.4  # metres kept between the camera and furniture reaching its height
_YAW_SWEEP = np.deg2rad(65.0)


def look_pose(position: np.ndarray, yaw: float, pitch: float, roll: float = 0.0) -> np.ndarray:  # (4, 4)
    """Camera-to-world pose at ``position`` looking along (yaw, pitch) in a z-up world, OpenCV axes.

    Args:
        position: ``(3,)`` camera centre.
        yaw: Heading in radians, counter-clockwise from +x.
        pitch: Elevation in radians (negative looks down).
        roll: Rotation about the viewing direction in radians.
    """
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = position
    return pose


def loop_path(room: np.ndarray, count: int = 2000, inset: float | None = None) -> np.ndarray:  # (count, 2)
    """Dense rounded rectangle (a superellipse) inset from the walls by ``inset`` metres.

    The default inset is a quarter of the room's side, kept within 0.9-1.6 m.
    """
    margin = np.clip(0.25 * room[:2], 0.9, 1.6) if inset is None else np.full(2, inset)
    half = np.maximum(room[:2] / 2 - margin, 0.15)
    theta = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    c, s = np.cos(theta), np.sin(theta)
    return room[:2] / 2 + half * np.stack([np.sign(c) * np.abs(c) ** 0.5, np.sign(s) * np.abs(s) ** 0.5], 1)


def _stations(path: np.ndarray, n: int, uneven: float, rng: np.random.Generator) -> np.ndarray:  # (n, 2)
    """``n`` positions along the closed path, with step lengths drawn more or less unevenly."""
    seg = np.linalg.norm(np.roll(path, -1, axis=0) - path, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    steps = rng.gamma(1.0 / max(uneven, 1e-3) ** 2, size=n) if uneven > 0 else np.ones(n)
    s = (np.cumsum(steps) - steps[0]) / steps.sum() * arc[-1] + rng.uniform(0, arc[-1])
    s = np.mod(s, arc[-1])
    closed = np.vstack([path, path[:1]])
    return np.stack([np.interp(s, arc, closed[:, 0]), np.interp(s, arc, closed[:, 1])], 1)


def push_clear(
    xy: np.ndarray, layout: Layout, min_top: float = _HEIGHT[0] - 0.5, clearance: float = _CLEARANCE
) -> np.ndarray:
    """Move positions towards the room centre until no box higher than ``min_top`` is within ``clearance``."""
    b = layout.boxes
    tall = np.arange(NUM_STUFF, len(b.yaw))
    tall = tall[b.centers[tall, 2] + b.half[tall, 2] > min_top]
    centre = layout.room[:2] / 2
    out = xy.copy()
    for _ in range(30):
        rel = out[:, None, :] - b.centers[None, tall, :2]
        c, s = np.cos(b.yaw[tall]), np.sin(b.yaw[tall])
        lx = np.abs(c * rel[..., 0] + s * rel[..., 1]) - b.half[tall, 0]
        ly = np.abs(-s * rel[..., 0] + c * rel[..., 1]) - b.half[tall, 1]
        dist = np.hypot(np.maximum(lx, 0), np.maximum(ly, 0))
        near = (dist < clearance).any(axis=1) if len(tall) else np.zeros(len(out), bool)
        if not near.any():
            break
        step = centre - out[near]
        out[near] += 0.1 * step / np.maximum(np.linalg.norm(step, axis=1, keepdims=True), 1e-6)
    return out


def make_trajectory(
    layout: Layout, num_frames: int, noise: TrajectoryNoise, rng: np.random.Generator
) -> np.ndarray:  # (V, 4, 4)
    """Camera-to-world poses of a walk around the room.

    Args:
        layout: The room.
        num_frames: Number of poses ``V``.
        noise: Handheld jitter and step unevenness.
        rng: Source of all random choices.

    Returns:
        ``(V, 4, 4)`` float64 poses, OpenCV camera axes.
    """
    xy = _stations(loop_path(layout.room), num_frames, noise.uneven, rng)
    phase = np.linspace(0.0, 1.0, num_frames, endpoint=False)
    height = 1.5 + 0.15 * np.sin(2 * np.pi * (2 * phase + rng.uniform()))
    xy = push_clear(xy + rng.normal(0, noise.position_m, xy.shape), layout)
    height = np.clip(height + rng.normal(0, noise.position_m, num_frames), *_HEIGHT)
    to_centre = layout.room[:2] / 2 - xy
    yaw = np.arctan2(to_centre[:, 1], to_centre[:, 0])
    yaw = yaw + _YAW_SWEEP * np.sin(2 * np.pi * (rng.uniform(2.5, 4.0) * phase + rng.uniform()))
    pitch = np.deg2rad(-16.0 + 14.0 * np.sin(2 * np.pi * (rng.uniform(1.5, 3.0) * phase + rng.uniform())))
    jitter = np.deg2rad(rng.normal(0, noise.rotation_deg, (num_frames, 3)))
    return np.stack([
        look_pose(np.array([x, y, z]), a + j[0], p + j[1], j[2])
        for (x, y), z, a, p, j in zip(xy, height, yaw, pitch, jitter)
    ])  # fmt: skip
