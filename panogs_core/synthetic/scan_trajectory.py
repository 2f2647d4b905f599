"""The dense handheld trajectory of a realistic scene (preset ``scan``): a full-rate video of a room scan.

A person scanning a room walks once around it 1.2-1.5 m from the walls at a speed that drifts between
lingering and hurrying, facing mostly outwards (at the walls and the furniture along them), panning left and
right (+-75 degrees, 18-26 sweeps per loop), now and then turning to the middle of the room (+-70 degrees,
2-3.5 times per loop), with the camera pointing down 14-34 degrees (so the ceiling is rarely seen). Every
few poses they glance somewhere for a moment (3-8 poses): crouch to look under a table, lift the camera over
a wardrobe, turn aside to a corner. The mesh of a real capture is fused from every frame of such a video and
the key frames are a sparse subset, so what only a glance or a hurried stretch saw is in the geometry but
seen by few or no key frames.

Positions are kept 0.3 m clear of every piece of furniture higher than 0.35 m, so that crouching never puts the
camera inside a table. Poses are camera-to-world with OpenCV axes.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from panogs_core.synthetic.layout import Layout
from panogs_core.synthetic.presets import TrajectoryNoise
from panogs_core.synthetic.trajectory import look_pose, loop_path, push_clear

_HEIGHT = 1.45  # mean camera height, metres
_PITCH = np.deg2rad(-24.0)  # mean pitch
_PITCH_SWING = np.deg2rad(10.0)  # amplitude of its up-and-down sweep
_PAN = np.deg2rad(75.0)  # amplitude of the fast left-right pan around the outward heading
_TURN = np.deg2rad(70.0)  # amplitude of the slow turn (towards the middle of the room at its extremes)
_INSET = (1.2, 1.5)  # distance of the walk from the walls, metres
_GLANCE_EVERY = 9  # mean dense poses between the starts of two glances
_GLANCE_LENGTH = (3, 8)  # dense poses a glance lasts
_GLANCE_KINDS = (0.35, 0.3, 0.35)  # probabilities of crouch, lift, turn aside
_SPEED_POSES, _SPEED_SPREAD = 60.0, 1.3  # walking speed: correlation (poses) and spread (log) of its drift
_CLEAR_TOP, _CLEAR_M = 0.35, 0.3  # furniture higher than this keeps the camera this far away


def _walk(path: np.ndarray, n: int, uneven: float, rng: np.random.Generator) -> np.ndarray:  # (n, 2)
    """``n`` positions once around the closed path, at a walking speed that drifts between slow and fast.

    The log of the speed is a smooth random signal (correlated over ``_SPEED_POSES`` poses, standard deviation
    ``_SPEED_SPREAD``): the person lingers at some places and hurries past others, so key frames taken every
    n-th pose are unevenly spaced along the walk. On top, every step varies with ``uneven`` as in
    ``trajectory._stations``.
    """
    seg = np.linalg.norm(np.roll(path, -1, axis=0) - path, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    drift = gaussian_filter1d(rng.standard_normal(n), _SPEED_POSES, mode="wrap")
    steps = np.exp(_SPEED_SPREAD * drift / max(float(drift.std()), 1e-9))
    if uneven > 0:
        steps = steps * rng.gamma(1.0 / uneven**2, uneven**2, size=n)
    s = np.mod((np.cumsum(steps) - steps[0]) / steps.sum() * arc[-1] + rng.uniform(0, arc[-1]), arc[-1])
    closed = np.vstack([path, path[:1]])
    return np.stack([np.interp(s, arc, closed[:, 0]), np.interp(s, arc, closed[:, 1])], 1)


def _glances(n: int, rng: np.random.Generator) -> np.ndarray:  # (n, 3): height, pitch, yaw offsets
    """Short excursions: offsets of height (m), pitch and yaw (rad) per pose, smooth in and out."""
    out = np.zeros((n, 3))
    start = 0
    while True:
        start += int(rng.geometric(1.0 / _GLANCE_EVERY))
        length = int(rng.integers(_GLANCE_LENGTH[0], _GLANCE_LENGTH[1] + 1))
        if start + length > n:
            return out
        bump = np.sin(np.linspace(0.0, np.pi, length + 2)[1:-1])  # 0 -> 1 -> 0
        kind = rng.choice(3, p=_GLANCE_KINDS)
        if kind == 0:  # crouch, look under the furniture
            offset = (-rng.uniform(0.6, 0.95), np.deg2rad(rng.uniform(5.0, 15.0)), 0.0)
        elif kind == 1:  # lift the camera, look down on the tops
            offset = (rng.uniform(0.6, 0.85), -np.deg2rad(rng.uniform(10.0, 25.0)), 0.0)
        else:  # turn aside
            offset = (
                0.0,
                np.deg2rad(rng.uniform(-10.0, 0.0)),
                np.deg2rad(rng.uniform(60.0, 120.0)) * rng.choice([-1, 1]),
            )
        out[start : start + length] += bump[:, None] * np.array(offset)
        start += length


def make_scan_trajectory(
    layout: Layout, num_poses: int, noise: TrajectoryNoise, rng: np.random.Generator
) -> np.ndarray:  # (P, 4, 4)
    """Camera-to-world poses of a dense scan of the room (module docstring).

    Args:
        layout: The room.
        num_poses: Number of dense poses ``P`` (the written frames are a subset).
        noise: Handheld jitter and unevenness of the walking speed.
        rng: Source of every random choice.

    Returns:
        ``(P, 4, 4)`` float64 poses, OpenCV camera axes.
    """
    inset = rng.uniform(*_INSET)
    path = loop_path(layout.room, inset=inset)
    xy = _walk(path, num_poses, noise.uneven, rng)
    xy = xy + rng.normal(0, noise.position_m, xy.shape)
    xy = push_clear(xy, layout, min_top=_CLEAR_TOP, clearance=_CLEAR_M)
    phase = np.linspace(0.0, 1.0, num_poses, endpoint=False)
    glance = _glances(num_poses, rng)
    outward = np.arctan2(xy[:, 1] - layout.room[1] / 2, xy[:, 0] - layout.room[0] / 2)
    pan = _PAN * np.sin(2 * np.pi * (rng.uniform(18.0, 26.0) * phase + rng.uniform()))
    turn = _TURN * np.sin(2 * np.pi * (rng.uniform(2.0, 3.5) * phase + rng.uniform()))
    yaw = outward + pan + turn + glance[:, 2]
    pitch = _PITCH + _PITCH_SWING * np.sin(2 * np.pi * (rng.uniform(10.0, 16.0) * phase + rng.uniform()))
    height = _HEIGHT + 0.1 * np.sin(2 * np.pi * (rng.uniform(1.5, 3.0) * phase + rng.uniform()))
    height = np.clip(height + glance[:, 0] + rng.normal(0, noise.position_m, num_poses), 0.5, layout.room[2] - 0.25)
    jitter = np.deg2rad(rng.normal(0, noise.rotation_deg, (num_poses, 3)))
    pitch = np.clip(pitch + glance[:, 1] + jitter[:, 1], np.deg2rad(-75.0), np.deg2rad(15.0))
    return np.stack([
        look_pose(np.array([x, y, z]), a + j[0], p, j[2])
        for (x, y), z, a, p, j in zip(xy, height, yaw, pitch, jitter)
    ])  # fmt: skip
