"""Import a Replica scene in the NICE-SLAM layout (docs/method.md §1.2) into a scene bundle.

Source layout::

    <src>/results/frameXXXXXX.jpg    RGB (1200x680 in NICE-SLAM's copy)
    <src>/results/depthXXXXXX.png    uint16, metres = value / 6553.5
    <src>/traj.txt                   line n = frame n: 16 floats, row-major 4x4 camera-to-world, OpenCV axes
    <src>/cam_params.json            optional, or one folder up:
                                     {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}
    <src>/features/frameXXXXXX.npy   optional per frame (``XXXXXX.npy`` accepted too): (Hf, Wf, D) feature map
    <src>/masks/frameXXXXXX.png      optional per frame (``XXXXXX.png`` accepted too): 2D instance id map

Bundle ids are the ``XXXXXX`` digits. The bundle camera is the depth camera: the intrinsics are scaled to the
depth images' size (same field of view) when they were given for another size, and with ``resize`` the depth
is resampled by nearest neighbour to a chosen size (the reference uses 640x360).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.importers.common import (
    ImportReport,
    SourceFrame,
    feature_dim_of,
    png_info,
    require_empty,
    write_import,
)
from panogs_core.progress import ProgressFn
from panogs_core.types import Camera, Vocabulary

logger = logging.getLogger(__name__)

# NICE-SLAM's Replica intrinsics (docs/method.md §1.2), used when no argument nor cam_params.json gives any.
NICE_SLAM_REPLICA_CAMERA = Camera(width=1200, height=680, fx=600.0, fy=600.0, cx=599.5, cy=339.5)
NICE_SLAM_DEPTH_SCALE = 6553.5
_DEPTH_NAME = re.compile(r"^depth(\d+)\.png$", re.IGNORECASE)


def import_replica(
    src: str | Path,
    dst: str | Path,
    *,
    stride: int = 1,
    camera: Camera | None = None,
    depth_scale: float | None = None,
    vocabulary: Vocabulary | None = None,
    geometry: str | Path | None = None,
    ground_truth: str | Path | None = None,
    feature_space: str = "clip-vit-b32",
    name: str | None = None,
    resize: tuple[int, int] | None = None,
    on_progress: ProgressFn | None = None,
) -> ImportReport:
    """Convert a NICE-SLAM Replica scene folder into a bundle at ``dst``.

    Args:
        src: Scene folder with ``results/`` and ``traj.txt`` (+ ``features/``, ``masks/``).
        dst: Bundle folder to create (must not exist or be empty).
        stride: Keep every ``stride``-th frame of the sorted list (Replica reference: 10).
        camera: Intrinsics; default ``cam_params.json`` (in ``src`` or its parent), else NICE-SLAM's
            1200x680 camera. When given, the depth is resampled to its size if it differs.
        depth_scale: Depth PNG value per metre; default the ``scale`` of ``cam_params.json``, else 6553.5.
        vocabulary: Label set to write as ``vocabulary.json`` (+ embeddings), or None.
        geometry: Mesh or point cloud (e.g. ``<scene>_trimesh.ply``) copied as ``geometry.ply``, or None.
        ground_truth: Labels for evaluation written as ``gt/labels.npz``: an ``.npz`` (``semantic``,
            ``instance``, optional ``points``) or ScanNet's ``<scene>_vh_clean_2.labels.ply`` with its
            aggregation and segments files beside it (then the vocabulary must be, or defaults to, ScanNet-20).
            See :mod:`panogs_core.io.ground_truth`.
        feature_space: ``features.space`` id of the feature maps.
        name: Scene name; the source folder name by default.
        resize: ``(width, height)`` to resample depth to (nearest neighbour), intrinsics scaled to match.
        on_progress: Called with ``(done, total)`` per frame.

    Returns:
        What was written and skipped.

    Raises:
        InputError: for a missing ``results/`` or ``traj.txt``, no feature maps, unreadable files, ``dst`` not
            empty, or ground truth that does not match the vocabulary or the geometry.
    """
    src, dst = Path(src), Path(dst)
    if stride < 1:
        raise InputError(f"import_replica: stride must be >= 1, got {stride}")
    require_empty(dst)
    depth_by_digits = _depth_files(src / "results")
    if not depth_by_digits:
        raise InputError(f"import_replica: {src / 'results'} has no depthXXXXXX.png images")
    every = sorted(depth_by_digits, key=int)
    digits = every[::stride]
    chosen = set(digits)
    params = _cam_params(src)
    source_cam = camera or params[0] or NICE_SLAM_REPLICA_CAMERA
    scale = depth_scale or params[1] or NICE_SLAM_DEPTH_SCALE
    target_cam = _target_camera(source_cam, depth_by_digits[digits[0]], resize, explicit=camera is not None)
    poses = _read_trajectory(src / "traj.txt")
    frames = [_source_frame(src, d, depth_by_digits[d], poses) for d in digits]
    dim = feature_dim_of([f.features for f in frames if f.features is not None], src / "features")
    result = write_import(
        dst,
        frames,
        name=name or src.name,
        camera=target_cam,
        depth_scale=scale,
        feature_dim=dim,
        feature_space=feature_space,
        geometry=geometry,
        vocabulary=vocabulary,
        ground_truth=ground_truth,
        skipped=[_pose_only(d, poses) for d in every if d not in chosen],
        on_progress=on_progress,
    )
    logger.info("import_replica: %s", result.summary())
    return result


def _target_camera(source: Camera, first_depth: Path, resize: tuple[int, int] | None, *, explicit: bool) -> Camera:
    """The bundle camera: ``resize`` if given, else an explicit camera's size, else the depth images' size."""
    if resize is not None:
        width, height = resize
    elif explicit:
        width, height = source.width, source.height
    else:
        width, height, _, _ = png_info(first_depth)
    if (width, height) != (source.width, source.height):
        logger.info(
            "import_replica: intrinsics scaled from %dx%d to %dx%d",
            source.width,
            source.height,
            width,
            height,
        )
    return source.scaled(width, height)


def _depth_files(results: Path) -> dict[str, Path]:
    if not results.is_dir():
        return {}
    found = {}
    for path in results.iterdir():
        match = _DEPTH_NAME.match(path.name)
        if match:
            found[match.group(1)] = path
    return found


def _pose_only(digits: str, poses: list[np.ndarray | None]) -> SourceFrame:
    """A frame the stride left out, by its pose only (``skipped_frames``). No gravity ``up`` is written: NICE-SLAM's
    trajectory does not document its world's up, so the pipeline estimates it."""
    index = int(digits)
    return SourceFrame(id=digits, T_world_cam=poses[index] if index < len(poses) else None, depth=None)


def _source_frame(src: Path, digits: str, depth: Path, poses: list[np.ndarray | None]) -> SourceFrame:
    index = int(digits)
    return SourceFrame(
        id=digits,
        T_world_cam=poses[index] if index < len(poses) else None,
        depth=depth,
        color=_first_existing(src / "results", [f"frame{digits}"], (".jpg", ".jpeg", ".png")),
        features=_first_existing(src / "features", [f"frame{digits}", digits, str(index)], (".npy",)),
        masks=_first_existing(src / "masks", [f"frame{digits}", digits, str(index)], (".png",)),
    )


def _first_existing(folder: Path, stems: list[str], exts: tuple[str, ...]) -> Path | None:
    for stem in stems:
        for ext in exts:
            path = folder / f"{stem}{ext}"
            if path.is_file():
                return path
    return None


def _read_trajectory(path: Path) -> list[np.ndarray | None]:  # per line: (4, 4), NaN-filled if malformed
    """One pose per line; a malformed line gives a NaN pose so that its frame is reported as invalid."""
    if not path.is_file():
        raise InputError(f"import_replica: {path} is missing (one 4x4 camera-to-world pose per line)")
    poses: list[np.ndarray | None] = []
    for line in path.read_text().splitlines():
        try:
            values = np.array([float(v) for v in line.split()], dtype=np.float64)
        except ValueError:
            values = np.empty(0)
        poses.append(values.reshape(4, 4) if values.size == 16 else np.full((4, 4), np.nan))
    return poses


def _cam_params(src: Path) -> tuple[Camera | None, float | None]:
    """(camera, depth scale) from NICE-SLAM's ``cam_params.json`` in ``src`` or its parent, if present."""
    for path in (src / "cam_params.json", src.parent / "cam_params.json"):
        if not path.is_file():
            continue
        try:
            cam = json.loads(path.read_text())["camera"]
            camera = Camera(
                width=int(cam["w"]),
                height=int(cam["h"]),
                fx=float(cam["fx"]),
                fy=float(cam["fy"]),
                cx=float(cam["cx"]),
                cy=float(cam["cy"]),
            )
            scale = float(cam["scale"]) if "scale" in cam else None
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(
                f"import_replica: {path}: expected {{'camera': {{w, h, fx, fy, cx, cy}}}} ({exc})"
            ) from exc
        return camera, scale
    return None, None
