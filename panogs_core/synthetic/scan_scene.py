"""The realistic branch of ``make_scene`` (preset ``scan``): a scene that behaves like a real room capture.

1. A dense handheld trajectory (``scan_trajectory.py``) of ``num_frames * dense_factor`` poses; every
   ``dense_factor``-th pose is a written frame, every ``key_frame_stride``-th written frame a key frame.
2. The geometry keeps the surface points that any dense pose observes (rendered at half resolution, not
   written), as a real mesh is fused from every frame of the video: surfaces only glanced at between two key
   frames are in it, seen by no key frame. No pose is re-aimed to cover what the key frames miss.
3. Ground truth: clutter and the ceiling are unannotated (-1), and blobs holding ``unannotated_stuff`` of the
   wall and floor points too (annotators skip segments of a real mesh).
4. Features: the instance model of ``features.py`` with related-class confusions, clutter features and
   world-anchored confusion regions (``anchored.py``).
5. The written poses are off the rendered ones by ``pose_error_m`` / ``pose_error_deg`` (registration error).
6. ``invalid_poses`` consecutive key frames (and the frames between them) are not written, as an importer drops
   the frames whose tracking failed; the geometry keeps what they saw.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.progress import ProgressFn
from panogs_core.synthetic.anchored import make_anchors, synthesize_anchored_features, with_clutter
from panogs_core.synthetic.catalog import CLASS_ID
from panogs_core.synthetic.coverage import coarse_camera
from panogs_core.synthetic.features import make_feature_model
from panogs_core.synthetic.frames import Streams, observed_in_view, subset, write_frames, write_static
from panogs_core.synthetic.layout import Layout
from panogs_core.synthetic.presets import Difficulty, SyntheticSpec, TrajectoryNoise
from panogs_core.synthetic.render import Render, render_view
from panogs_core.synthetic.sampling import SurfacePoints
from panogs_core.synthetic.scan_trajectory import make_scan_trajectory
from panogs_core.types import Camera

_DENSE_DIVISOR = 2  # the dense poses are rendered at 1/2 resolution to decide what the mesh holds
_DENSE_RTOL = 0.04  # depth tolerance there: a coarse pixel's ray lands up to a few cm off the point
_HOLE_RADIUS = (0.3, 0.8)  # radii of the unannotated blobs of wall and floor, metres


def write_scan_scene(
    writer: BundleWriter,
    scene: o3d.t.geometry.RaycastingScene,
    layout: Layout,
    surface: SurfacePoints,
    embeddings: np.ndarray,
    spec: SyntheticSpec,
    level: Difficulty,
    rng: Streams,
    with_geometry: bool,
    on_progress: ProgressFn | None,
) -> None:
    """Write the frames, geometry, ground truth and vocabulary of a realistic scene (module docstring).

    Args:
        writer: The open bundle.
        scene: Ray-casting scene of the layout.
        layout: The room (``build_scan_layout``).
        surface: Its surface samples (before keeping the observed ones).
        embeddings: Class text embeddings ``(L, D)``.
        spec: A realistic spec.
        level: The difficulty (realistic strengths).
        rng: The random streams of the scene.
        with_geometry: Write ``geometry.ply`` (else the ground truth carries the points).
        on_progress: Called per written frame.
    """
    holes_rng, clutter_rng, anchors_rng, poses_rng = rng.realism.spawn(4)  # one stream per purpose
    dense = make_scan_trajectory(layout, spec.num_frames * spec.dense_factor, level.trajectory, rng.trajectory)
    poses = dense[:: spec.dense_factor]
    kept = subset(surface, observe_dense(scene, layout, writer.camera, dense, surface))
    annotated = layout.annotated if layout.annotated is not None else np.ones(len(layout.instance_class), bool)
    kept = _unannotate(kept, annotated, spec.unannotated_stuff, holes_rng)
    model = make_feature_model(embeddings, layout.instance_class, level.features, rng.features, related=True)
    model = with_clutter(model, annotated, clutter_rng)
    noise = level.features
    anchors = make_anchors(kept.points, kept.semantic, noise.anchored_area, noise.anchored_weight,
                           noise.anchored_radius_m, anchors_rng)  # fmt: skip
    shape = (spec.height // spec.feature_stride, spec.width // spec.feature_stride)
    camera = writer.camera

    def features(instance: np.ndarray, view: Render, pose: np.ndarray, frame_rng: np.random.Generator) -> np.ndarray:
        world = pixel_world(view.depth, camera, pose)
        return synthesize_anchored_features(model, anchors, annotated, instance, world, shape, frame_rng)

    written = perturb_poses(poses, level.trajectory, poses_rng)
    lost = lost_frames(len(poses), spec.key_frame_stride, spec.invalid_poses, rng.realism)
    write_frames(writer, scene, layout, features, poses, spec, level, rng.frames, surface, on_progress, written, lost)
    write_static(writer, kept, embeddings, with_geometry)


def lost_frames(num_frames: int, key_stride: int, count: int, rng: np.random.Generator) -> frozenset[int]:
    """Indices of the written frames a tracking failure loses: ``count`` consecutive key frames and the frames
    between them, at a random place in the capture (none when ``count`` is 0, and no draw then)."""
    if count <= 0:
        return frozenset()
    keys = np.arange(0, num_frames, key_stride)
    first = int(rng.integers(0, len(keys) - count + 1))
    return frozenset(range(int(keys[first]), int(keys[first + count - 1]) + 1))


def observe_dense(
    scene: o3d.t.geometry.RaycastingScene, layout: Layout, camera: Camera, poses: np.ndarray, surface: SurfacePoints
) -> np.ndarray:  # (N,) bool
    """Which surface points any of ``poses`` observes, rendered at ``1 / _DENSE_DIVISOR`` resolution."""
    coarse = coarse_camera(camera, _DENSE_DIVISOR)
    observed = np.zeros(len(surface.points), dtype=bool)
    for pose in poses:
        view = render_view(scene, layout, coarse, pose, shade=False)
        observed[observed_in_view(surface, layout, coarse, pose, view, _DENSE_RTOL)] = True
    return observed


def pixel_world(depth: np.ndarray, camera: Camera, pose: np.ndarray) -> np.ndarray:  # (H, W, 3)
    """World point of every pixel of a clean z-depth image (pixels without depth land on the camera)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    cam = np.stack([(u - camera.cx) / camera.fx * depth, (v - camera.cy) / camera.fy * depth, depth], axis=-1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def perturb_poses(poses: np.ndarray, noise: TrajectoryNoise, rng: np.random.Generator) -> np.ndarray:  # (V, 4, 4)
    """The poses with a Gaussian registration error: translation per axis, rotation about a random axis."""
    out = poses.copy()
    shift = rng.normal(0.0, noise.pose_error_m, (len(poses), 3))
    turn = np.deg2rad(rng.normal(0.0, noise.pose_error_deg, (len(poses), 3)))
    for k in range(len(poses)):
        out[k, :3, :3] = poses[k, :3, :3] @ _rotation(turn[k])
        out[k, :3, 3] += shift[k]
    return out


def _rotation(rotvec: np.ndarray) -> np.ndarray:  # (3, 3)
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec / angle
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


def _unannotate(
    surface: SurfacePoints, annotated: np.ndarray, stuff_fraction: float, rng: np.random.Generator
) -> SurfacePoints:
    """Ground truth -1 for unannotated instances and for blobs of wall and floor (module docstring, 3)."""
    keep = annotated[surface.instance]
    stuff = np.flatnonzero(keep & np.isin(surface.semantic, [CLASS_ID["wall"], CLASS_ID["floor"]]))
    if stuff_fraction > 0 and len(stuff):
        tree, hole = cKDTree(surface.points[stuff]), np.zeros(len(stuff), dtype=bool)
        while hole.mean() < stuff_fraction:
            hole[tree.query_ball_point(surface.points[stuff[rng.integers(len(stuff))]], rng.uniform(*_HOLE_RADIUS))] = (
                True
            )
        keep[stuff[hole]] = False
    return replace(
        surface, semantic=np.where(keep, surface.semantic, -1), instance=np.where(keep, surface.instance, -1)
    )
