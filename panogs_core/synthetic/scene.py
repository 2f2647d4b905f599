"""``make_scene``: a complete synthetic scene bundle (docs/scene_format.md) from a preset, a difficulty and a seed.

Random streams are split from the seed per purpose (layout, surface points, trajectory, feature model,
frames), so the room and the surface points of a seed are the same at every difficulty, and a bundle is a pure
function of its arguments.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.progress import ProgressFn
from panogs_core.synthetic.catalog import label_embeddings
from panogs_core.synthetic.coverage import ensure_coverage
from panogs_core.synthetic.features import make_feature_model, synthesize_features
from panogs_core.synthetic.frames import Streams, subset, write_frames, write_static
from panogs_core.synthetic.presets import Difficulty, SyntheticSpec, get_difficulty, get_preset
from panogs_core.synthetic.render import Render, make_raycaster
from panogs_core.synthetic.rooms import build_layout
from panogs_core.synthetic.sampling import sample_surfaces
from panogs_core.synthetic.trajectory import make_trajectory
from panogs_core.types import Camera

DEPTH_SCALE = 1000.0


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
