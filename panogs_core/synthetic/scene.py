"""``make_scene``: a complete synthetic scene bundle (docs/scene_format.md) from a preset, a difficulty and a seed.

Random streams are split from the seed per purpose (layout, surface points, trajectory, feature model,
frames), so the room and the surface points of a seed are the same at every difficulty, and a bundle is a pure
function of its arguments.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from panogs_core.io.writer import BundleWriter
from panogs_core.progress import ProgressFn, report
from panogs_core.synthetic.catalog import catalogue_vocabulary, label_embeddings
from panogs_core.synthetic.coverage import ensure_coverage
from panogs_core.synthetic.degrade import degrade_color, degrade_depth
from panogs_core.synthetic.features import make_feature_model, synthesize_features
from panogs_core.synthetic.layout import Layout, build_layout
from panogs_core.synthetic.masks import synthesize_masks
from panogs_core.synthetic.presets import Difficulty, SyntheticSpec, get_difficulty, get_preset
from panogs_core.synthetic.render import Render, face_normals, make_raycaster, render_view
from panogs_core.synthetic.sampling import SurfacePoints, sample_surfaces
from panogs_core.synthetic.trajectory import make_trajectory
from panogs_core.types import Camera
from panogs_core.visibility import VisibilityConfig, frame_visibility

DEPTH_SCALE = 1000.0


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


def _streams(seed: int, num_frames: int) -> Streams:
    layout, points, trajectory, features, frames, realism = np.random.SeedSequence(seed).spawn(6)
    return Streams(
        layout=np.random.default_rng(layout),
        points=np.random.default_rng(points),
        trajectory=np.random.default_rng(trajectory),
        features=np.random.default_rng(features),
        frames=frames.spawn(num_frames),
        realism=np.random.default_rng(realism),
    )


def spec_camera(spec: SyntheticSpec) -> Camera:
    """The pinhole camera of a spec (square pixels, principal point at the image centre)."""
    f = spec.width / 2 / np.tan(np.deg2rad(spec.hfov_deg) / 2)
    return Camera(width=spec.width, height=spec.height, fx=float(f), fy=float(f),
                  cx=(spec.width - 1) / 2, cy=(spec.height - 1) / 2)  # fmt: skip


def make_scene(
    out_dir: str | Path,
    *,
    preset: str | SyntheticSpec = "tiny",
    difficulty: str | Difficulty = "default",
    seed: int = 0,
    feature_space: str | None = None,
    with_geometry: bool = True,
    name: str | None = None,
    on_progress: ProgressFn | None = None,
) -> Path:
    """Generate a synthetic indoor scene and write it as a bundle.

    Args:
        out_dir: Bundle folder to write (created).
        preset: ``tiny``, ``small``, ``default``, ``large``, ``scan`` or a :class:`SyntheticSpec`.
        difficulty: ``easy``, ``default``, ``hard`` or a :class:`Difficulty`; for a realistic spec
            (``scan``) a name is looked up in ``REALISTIC_DIFFICULTIES``.
        seed: Seed of every random choice; the same arguments give the same bundle.
        feature_space: ``minilm-l6`` or ``clip-vit-b32``; None takes the preset's (``clip-vit-b32`` for
            ``large`` and ``scan``, ``minilm-l6`` otherwise).
        with_geometry: Write ``geometry.ply`` (the surface points). Without it, the ground truth carries the
            points themselves, for pipelines that build primitives from the depth frames.
        name: Scene name; default ``synthetic-<preset>-<difficulty>-<seed>``.
        on_progress: Called as ``on_progress(frames_done, num_frames)``.

    Returns:
        The bundle folder.

    Raises:
        ConfigError: for an unknown preset or difficulty.
        ValueError: for an unknown feature space.
        EncoderUnavailableError: for ``minilm-l6`` without the text encoder installed.

    Example:
        >>> import tempfile
        >>> root = make_scene(tempfile.mkdtemp(), preset="tiny", feature_space="clip-vit-b32")
        >>> sorted(p.name for p in root.iterdir())[:4]
        ['color', 'depth', 'features', 'geometry.ply']
    """
    spec = get_preset(preset)
    level = get_difficulty(difficulty, realistic=spec.realistic)
    space = feature_space or spec.feature_space
    embeddings = label_embeddings(space)
    rng = _streams(seed, spec.num_frames)
    layout = build_layout(spec, rng.layout)
    surface = sample_surfaces(layout, spec.num_points, rng.points)
    camera, scene = spec_camera(spec), make_raycaster(layout)
    scene_name = name or f"synthetic-{spec.name}-{level.name}-{seed}"
    if spec.realistic:
        from panogs_core.synthetic.scan_scene import write_scan_scene  # it builds on this module

        writer = _writer(out_dir, scene_name, camera, embeddings, space)
        write_scan_scene(writer, scene, layout, surface, embeddings, spec, level, rng, with_geometry, on_progress)
        return writer.close()
    poses = make_trajectory(layout, spec.num_frames, level.trajectory, rng.trajectory)
    poses = ensure_coverage(scene, layout, camera, poses, np.arange(0, spec.num_frames, spec.key_frame_stride))
    model = make_feature_model(embeddings, layout.instance_class, level.features, rng.features)
    writer = _writer(out_dir, scene_name, camera, embeddings, space)
    shape = (spec.height // spec.feature_stride, spec.width // spec.feature_stride)

    def features(instance: np.ndarray, view: Render, pose: np.ndarray, frame_rng: np.random.Generator) -> np.ndarray:
        return synthesize_features(model, instance, shape, frame_rng)

    observed = write_frames(writer, scene, layout, features, poses, spec, level, rng.frames, surface, on_progress)
    write_static(writer, subset(surface, observed), embeddings, with_geometry)
    return writer.close()


def _writer(out_dir: str | Path, name: str, camera: Camera, embeddings: np.ndarray, space: str) -> BundleWriter:
    """A new bundle for a synthetic scene (depth in millimetres)."""
    return BundleWriter(out_dir, name=name, camera=camera, depth_scale=DEPTH_SCALE,
                        feature_dim=embeddings.shape[1], feature_space=space)  # fmt: skip


def write_frames(
    writer: BundleWriter, scene: o3d.t.geometry.RaycastingScene, layout: Layout, features: FeatureFn,
    poses: np.ndarray, spec: SyntheticSpec, level: Difficulty, seeds: list[np.random.SeedSequence],
    surface: SurfacePoints, on_progress: ProgressFn | None, written_poses: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """Render, degrade and write every frame; key frames also get features and masks.

    ``features(instance, view, pose, rng)`` makes a key frame's feature map. Frames are rendered at
    ``poses``; ``written_poses`` (default: the same) are the poses the bundle records.

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
