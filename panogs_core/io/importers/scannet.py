"""Import a ScanNet export (SensReader layout, docs/method.md §1.3) into a scene bundle.

Source layout::

    <src>/color/<i>.jpg                     RGB, any size (1296x968 in ScanNet v2)
    <src>/depth/<i>.png                     uint16 millimetres, 640x480
    <src>/pose/<i>.txt                      4x4 camera-to-world, OpenCV axes; ``-inf`` when tracking was lost
    <src>/intrinsic/intrinsic_depth.txt     4x4 (or 3x3) pinhole matrix of the depth camera
    <src>/features/<i>.npy                  optional per frame: (Hf, Wf, D) 2D feature map
    <src>/masks/<i>.png                     optional per frame: 2D instance id map

Frames are ordered by the integer stem ``<i>``; bundle ids are ``<i>`` zero-padded to six digits. Frames whose
pose is not a finite rigid transform are skipped and reported (the reference keeps them, docs/method.md §10).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.importers.common import (
    ImportReport,
    SourceFrame,
    feature_dim_of,
    png_info,
    read_matrix,
    require_empty,
    write_import,
)
from panogs_core.progress import ProgressFn
from panogs_core.types import Camera, Vocabulary

logger = logging.getLogger(__name__)

SCANNET_DEPTH_SCALE = 1000.0  # millimetres


def import_scannet(
    src: str | Path,
    dst: str | Path,
    *,
    stride: int = 1,
    vocabulary: Vocabulary | None = None,
    geometry: str | Path | None = None,
    ground_truth: str | Path | None = None,
    name: str | None = None,
    feature_space: str = "clip-vit-b32",
    camera: Camera | None = None,
    on_progress: ProgressFn | None = None,
) -> ImportReport:
    """Convert a ScanNet export folder into a bundle at ``dst``.

    Args:
        src: Scene folder with ``color/``, ``depth/``, ``pose/``, ``intrinsic/`` (+ ``features/``,
            ``masks/``).
        dst: Bundle folder to create (must not exist or be empty).
        stride: Keep every ``stride``-th frame of the sorted list (ScanNet reference: 20).
        vocabulary: Label set to write as ``vocabulary.json`` (+ embeddings), or None.
        geometry: Mesh or point cloud (e.g. ``<scene>_vh_clean_2.ply``) copied as ``geometry.ply``, or None.
        ground_truth: Labels for evaluation written as ``gt/labels.npz``: an ``.npz`` (``semantic``,
            ``instance``, optional ``points``) or ScanNet's ``<scene>_vh_clean_2.labels.ply`` with its
            aggregation and segments files beside it (then the vocabulary must be, or defaults to, ScanNet-20).
            See :mod:`panogs_core.io.ground_truth`.
        name: Scene name; the source folder name by default.
        feature_space: ``features.space`` id of the feature maps.
        camera: Override of ``intrinsic_depth.txt`` (its size must be the depth size).
        on_progress: Called with ``(done, total)`` per frame.

    Returns:
        What was written and skipped.

    Raises:
        InputError: for a missing folder or intrinsics, no feature maps, unreadable files, ``dst`` not empty,
            or ground truth that does not match the vocabulary or the geometry.
    """
    src, dst = Path(src), Path(dst)
    if stride < 1:
        raise InputError(f"import_scannet: stride must be >= 1, got {stride}")
    require_empty(dst)
    depth_by_index = _indexed_files(src / "depth", ".png")
    if not depth_by_index:
        raise InputError(f"import_scannet: {src / 'depth'} has no <i>.png depth images")
    every = sorted(depth_by_index)
    indices = every[::stride]
    first_depth = depth_by_index[indices[0]]
    cam = camera if camera is not None else _read_intrinsics(src, first_depth)
    frames = [_source_frame(src, i, depth_by_index[i]) for i in indices]
    dim = feature_dim_of([f.features for f in frames if f.features is not None], src / "features")
    result = write_import(
        dst,
        frames,
        name=name or src.name,
        camera=cam,
        depth_scale=SCANNET_DEPTH_SCALE,
        feature_dim=dim,
        feature_space=feature_space,
        geometry=geometry,
        vocabulary=vocabulary,
        ground_truth=ground_truth,
        skipped=_left_out(src, every, set(indices), depth_by_index),
        on_progress=on_progress,
    )
    logger.info("import_scannet: %s", result.summary())
    return result


def _source_frame(src: Path, index: int, depth: Path) -> SourceFrame:
    return SourceFrame(
        id=f"{index:06d}",
        T_world_cam=_read_pose(src / "pose" / f"{depth.stem}.txt"),
        depth=depth,
        color=_first_existing(src / "color", depth.stem, index, (".jpg", ".jpeg", ".png")),
        features=_first_existing(src / "features", depth.stem, index, (".npy",)),
        masks=_first_existing(src / "masks", depth.stem, index, (".png",)),
    )


def _left_out(src: Path, every: list[int], chosen: set[int], depth_by_index: dict[int, Path]) -> list[SourceFrame]:
    """The frames the stride left out, by their pose only (``skipped_frames``); no gravity ``up`` is written: the
    SensReader poses are in the reconstruction's frame, which the export does not document as gravity-aligned."""
    return [
        SourceFrame(id=f"{i:06d}", T_world_cam=_read_pose(src / "pose" / f"{depth_by_index[i].stem}.txt"), depth=None)
        for i in every
        if i not in chosen
    ]


def _indexed_files(folder: Path, ext: str) -> dict[int, Path]:
    """Files ``<integer>.<ext>`` of a folder by integer stem; other names are ignored."""
    if not folder.is_dir():
        return {}
    found: dict[int, Path] = {}
    for path in folder.iterdir():
        if path.suffix.lower() == ext and path.stem.isdigit():
            found.setdefault(int(path.stem), path)
    return found


def _first_existing(folder: Path, stem: str, index: int, exts: tuple[str, ...]) -> Path | None:
    """``<stem>.<ext>`` or the zero-padded ``<index:06d>.<ext>`` in ``folder``, whichever exists first."""
    for candidate in (stem, str(index), f"{index:06d}"):
        for ext in exts:
            path = folder / f"{candidate}{ext}"
            if path.is_file():
                return path
    return None


def _read_pose(path: Path) -> np.ndarray | None:  # (4, 4) or None when missing/unparseable
    pose = read_matrix(path)
    if pose is None or pose.shape != (4, 4):
        if path.exists():
            logger.warning("import_scannet: %s is not a 4x4 matrix", path)
            return np.full((4, 4), np.nan)  # counts as an invalid pose, not a missing one
        return None
    return pose


def _read_intrinsics(src: Path, first_depth: Path) -> Camera:
    path = src / "intrinsic" / "intrinsic_depth.txt"
    K = read_matrix(path)
    if K is None or K.shape not in ((3, 3), (4, 4)) or not np.all(np.isfinite(K[:3, :3])):
        raise InputError(f"import_scannet: {path} missing or not a 3x3/4x4 matrix")
    width, height, _, _ = png_info(first_depth)  # intrinsic_depth describes the depth image
    fx, fy, cx, cy = (float(K[r, c]) for r, c in ((0, 0), (1, 1), (0, 2), (1, 2)))
    return Camera(width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy)
