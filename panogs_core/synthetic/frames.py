"""The frames and static files of a synthetic bundle: render, degrade, write; shared by both kinds of scene.

``scene.py`` (the zoned rooms) and ``scan_scene.py`` (the realistic studio) both write their frames and their
geometry and ground truth with these, so neither has to import the other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.progress import ProgressFn, report
from panogs_core.stages.visibility import VisibilityConfig, frame_visibility
from panogs_core.synthetic.catalog import catalogue_vocabulary
from panogs_core.synthetic.degrade import degrade_color, degrade_depth
from panogs_core.synthetic.layout import Layout
from panogs_core.synthetic.masks import synthesize_masks
from panogs_core.synthetic.presets import Difficulty, SyntheticSpec
from panogs_core.synthetic.render import Render, face_normals, render_view
from panogs_core.synthetic.sampling import SurfacePoints
from panogs_core.types import Camera

FeatureFn = Callable[[np.ndarray, Render, np.ndarray, np.random.Generator], np.ndarray]


@dataclass(frozen=True)
class Streams:
    """Independent random generators, one per purpose."""

    layout: np.random.Generator
    points: np.random.Generator
    trajectory: np.random.Generator
    features: np.random.Generator
    frames: list[np.random.SeedSequence]
    realism: np.random.Generator  # realistic scenes only (a sixth child: the first five are as before)


def write_frames(
    writer: BundleWriter, scene: o3d.t.geometry.RaycastingScene, layout: Layout, features: FeatureFn,
    poses: np.ndarray, spec: SyntheticSpec, level: Difficulty, seeds: list[np.random.SeedSequence],
    surface: SurfacePoints, on_progress: ProgressFn | None, written_poses: np.ndarray | None = None,
    dropped: frozenset[int] = frozenset(),
) -> np.ndarray:  # fmt: skip
    """Render, degrade and write every frame; key frames also get features and masks.

    ``features(instance, view, pose, rng)`` makes a key frame's feature map. Frames are rendered at
    ``poses``; ``written_poses`` (default: the same) are the poses the bundle records. Frames whose index is in
    ``dropped`` are not written (an importer drops frames with invalid poses); the others keep their ids and draws.

    Returns which surface points any frame observes: a real capture's geometry holds only surfaces the
    camera saw, so the scene keeps only those (floor under a cabinet, the back of a bookshelf against a wall,
    the underside of a table top, the sides of two cabinets standing 5 mm apart are not in a scan). A point
    is observed when a ray hits its own face there: the pixel it projects to shows its box, through a face
    facing the same way, at its depth (clean depth, 2 % tolerance). A depth test alone would count hidden
    faces a few centimetres behind a visible one as seen.
    """
    camera = writer.camera
    observed = np.zeros(surface.points.shape[0], dtype=bool)
    written_poses = poses if written_poses is None else written_poses
    for i, (pose, seq) in enumerate(zip(poses, seeds)):
        if i in dropped:
            report(on_progress, i + 1, len(poses))
            continue
        rng = np.random.default_rng(seq)
        view = render_view(scene, layout, camera, pose)
        observed[observed_in_view(surface, layout, camera, pose, view)] = True
        instance = np.where(view.box >= 0, layout.box_instance[np.maximum(view.box, 0)], -1)
        feature_map = masks = None
        if i % spec.key_frame_stride == 0:
            feature_map = features(instance, view, pose, rng)
            masks = synthesize_masks(instance, view.box, view.face, layout, level.masks, rng)
        writer.add_frame(f"{i:06d}", written_poses[i], degrade_depth(view.depth, level.depth, rng),
                         color=degrade_color(view.color, level.color_noise, rng), features=feature_map,
                         masks=masks)  # fmt: skip
        report(on_progress, i + 1, len(poses))
    return observed


def observed_in_view(
    surface: SurfacePoints, layout: Layout, camera: Camera, pose: np.ndarray, view: Render, depth_rtol: float = 0.02
) -> np.ndarray:  # (n,) int32 surface point indices
    """The surface points a rendered view observes: the pixel a point projects to shows its own face.

    That is, its box, through a face facing the same way, at its depth (clean depth, ``depth_rtol``).
    """
    seen, row, col, _ = frame_visibility(
        surface.points,
        np.linalg.inv(pose),
        camera,
        view.depth.astype(np.float32),
        VisibilityConfig(depth_rtol=depth_rtol),
    )
    own_face = (view.box[row, col] == surface.box[seen]) & (
        np.einsum("ij,ij->i", face_normals(layout, view.box[row, col], view.face[row, col]),
                  surface.normals[seen]) > 0.5
    )  # fmt: skip
    return seen[own_face]


def subset(surface: SurfacePoints, keep: np.ndarray) -> SurfacePoints:
    """The surface points where ``keep`` is True, every field alike."""
    return SurfacePoints(
        points=surface.points[keep],
        normals=surface.normals[keep],
        colors=surface.colors[keep],
        semantic=surface.semantic[keep],
        instance=surface.instance[keep],
        box=surface.box[keep],
    )


def write_static(writer: BundleWriter, surface: SurfacePoints, embeddings: np.ndarray, with_geometry: bool) -> None:
    """Geometry, ground truth and vocabulary."""
    if with_geometry:
        writer.write_geometry(surface.points, colors=surface.colors, normals=surface.normals)
        writer.write_ground_truth(surface.semantic, surface.instance)
    else:
        writer.write_ground_truth(surface.semantic, surface.instance, points=surface.points)
    writer.write_vocabulary(catalogue_vocabulary(embeddings))
