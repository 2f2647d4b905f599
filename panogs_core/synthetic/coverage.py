"""Make sure every instance of a layout is seen by some key frame of a trajectory.

A short or uneven walk can miss an object (a shelf behind the camera's whole path). Each missed instance gets
a key frame turned towards it, as a person scanning a room turns to an object they skipped: the frame chosen
is one whose view no instance depends on, near enough to the object, and the turn is kept only if the object
then shows. Visibility is counted on quarter-resolution renders: cheap, and enough to tell seen from unseen.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from panogs_core.synthetic.layout import Layout
from panogs_core.synthetic.render import render_view
from panogs_core.synthetic.trajectory import look_pose
from panogs_core.types import Camera

_MIN_PIXELS = 4  # quarter-resolution pixels for an instance to count as seen (~64 full-resolution pixels)
_CANDIDATES = 8  # frames tried per missed instance
_PITCH_LIMIT = np.deg2rad((-60.0, 25.0))


def coarse_camera(camera: Camera, factor: int = 4) -> Camera:
    """The same field of view at 1/factor resolution (pixel centres kept consistent)."""
    return Camera(width=max(camera.width // factor, 8), height=max(camera.height // factor, 6),
                  fx=camera.fx / factor, fy=camera.fy / factor,
                  cx=(camera.cx + 0.5) / factor - 0.5, cy=(camera.cy + 0.5) / factor - 0.5)  # fmt: skip


def _counts(scene: o3d.t.geometry.RaycastingScene, layout: Layout, camera: Camera, pose: np.ndarray) -> np.ndarray:
    """Pixels per instance in one coarse view ``(I,)``."""
    box = render_view(scene, layout, camera, pose).box
    return np.bincount(layout.box_instance[box[box >= 0]], minlength=len(layout.instance_class))


def _instance_centres(layout: Layout) -> np.ndarray:  # (I, 3)
    """Volume-weighted centre of each instance's boxes."""
    vol = np.prod(layout.boxes.half, axis=1)
    n = len(layout.instance_class)
    weight = np.bincount(layout.box_instance, weights=vol, minlength=n)
    centre = np.stack(
        [np.bincount(layout.box_instance, weights=vol * layout.boxes.centers[:, k], minlength=n) for k in range(3)],
        1,
    )
    return centre / np.maximum(weight, 1e-12)[:, None]


def _aim(pose: np.ndarray, target: np.ndarray) -> np.ndarray:  # (4, 4)
    """The pose turned (yaw and pitch, no roll) to look at ``target`` from the same position."""
    d = target - pose[:3, 3]
    yaw = np.arctan2(d[1], d[0])
    pitch = np.clip(np.arctan2(d[2], np.hypot(d[0], d[1])), *_PITCH_LIMIT)
    return look_pose(pose[:3, 3], float(yaw), float(pitch))


def ensure_coverage(
    scene: o3d.t.geometry.RaycastingScene,
    layout: Layout,
    camera: Camera,
    poses: np.ndarray,  # (V, 4, 4)
    key_frames: np.ndarray,  # (K,) int frame indices
) -> np.ndarray:  # (V, 4, 4)
    """Turn key frames towards instances that no key frame sees.

    Args:
        scene: Ray-casting scene of the layout.
        layout: The room.
        camera: Full-resolution camera.
        poses: Camera-to-world poses of the trajectory.
        key_frames: Indices of the frames that get features and masks.

    Returns:
        The poses, with some key frames re-aimed; unchanged when every instance is already seen.
    """
    coarse, out = coarse_camera(camera), poses.copy()
    counts = np.stack([_counts(scene, layout, coarse, out[k]) for k in key_frames])  # (K, I)
    centres = _instance_centres(layout)
    for inst in np.flatnonzero((counts >= _MIN_PIXELS).sum(axis=0) == 0):
        seen_by = (counts >= _MIN_PIXELS).sum(axis=0)
        # frames whose every seen instance is also seen elsewhere can be turned without losing anything
        sole = ((counts >= _MIN_PIXELS) & (seen_by == 1)[None, :]).any(axis=1)
        dist = np.linalg.norm(out[key_frames, :3, 3] - centres[inst], axis=1)
        order = np.lexsort((np.abs(dist - 2.0), sole))
        for j in order[:_CANDIDATES]:
            pose = _aim(out[key_frames[j]], centres[inst])
            new = _counts(scene, layout, coarse, pose)
            only_here = (counts[j] >= _MIN_PIXELS) & (seen_by == 1)
            if new[inst] >= _MIN_PIXELS and (new[only_here] >= _MIN_PIXELS).all():
                out[key_frames[j]], counts[j] = pose, new
                break
    return out
