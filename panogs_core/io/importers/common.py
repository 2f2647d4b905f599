"""What the dataset importers share: the source frame, the import report, and the end of every import (a bundle
with optional geometry, vocabulary and ground truth, then the frames), plus the small readers of source files.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.bundle.format import MAX_PNG_VALUE
from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.io.ground_truth import load_ground_truth, vocabulary_for_ground_truth
from panogs_core.io.ply import read_ply_vertices
from panogs_core.progress import ProgressFn, report
from panogs_core.types import Camera, Vocabulary


@dataclass(frozen=True)
class ImportReport:
    """What an importer wrote, and what it left out and why.

    Attributes:
        bundle: The bundle folder written.
        frames_written: Frames in ``scene.json``.
        frames_skipped_invalid_pose: Ids of source frames dropped for a non-finite or non-rigid pose
            (ScanNet marks lost tracking with ``-inf`` poses).
        frames_skipped_missing: Ids of source frames dropped for a missing pose or depth.
        frames_without_features: Written frames that have no feature map.
        frames_without_masks: Written frames that have no mask image.
    """

    bundle: Path
    frames_written: int
    frames_skipped_invalid_pose: tuple[str, ...] = ()
    frames_skipped_missing: tuple[str, ...] = ()
    frames_without_features: int = 0
    frames_without_masks: int = 0

    def summary(self) -> str:
        """One human-readable paragraph, for the CLI."""
        lines = [f"wrote {self.frames_written} frames to {self.bundle}"]
        if self.frames_skipped_invalid_pose:
            lines.append(
                f"skipped {len(self.frames_skipped_invalid_pose)} frames with invalid poses: "
                + id_list(self.frames_skipped_invalid_pose)
            )
        if self.frames_skipped_missing:
            lines.append(
                f"skipped {len(self.frames_skipped_missing)} frames without pose or depth: "
                + id_list(self.frames_skipped_missing)
            )
        lines.append(
            f"{self.frames_without_features} frames without features, {self.frames_without_masks} without masks"
        )
        return "\n".join(lines)


@dataclass(frozen=True)
class SourceFrame:
    """One frame of a dataset layout, before import. ``None`` means absent."""

    id: str
    T_world_cam: np.ndarray | None  # (4, 4) camera-to-world as read; None when the pose is missing
    depth: Path | None
    color: Path | None = None
    features: Path | None = None
    masks: Path | None = None


def write_source_frames(
    writer: BundleWriter,
    frames: list[SourceFrame],
    *,
    skipped: Sequence[SourceFrame] = (),
    on_progress: ProgressFn | None = None,
) -> ImportReport:
    """Add dataset frames to a bundle, converting only what the format requires; then close the bundle.

    Depth PNGs already 16-bit at the camera size, colour images, 16/8-bit single-channel masks and
    float16/float32 C-order feature maps are copied unchanged. Depth at another size is resampled to the
    camera size by nearest neighbour (pixel centres, as the format's lookup rule); masks in colour are turned
    into ids; float64 or Fortran-order features are rewritten as float32 C order.

    Args:
        writer: An open writer whose camera is the target camera.
        frames: Source frames in manifest order.
        skipped: Source frames the stride left out: those with a valid pose are recorded by their pose only
            (``skipped_frames``, docs/scene_format.md §2.6), so that ``panogs render RUN --frame ID`` reaches every
            frame of the capture, as the capture importers do; their depth is not read.
        on_progress: Called with ``(done, total)`` after each frame.

    Returns:
        The report; ``bundle`` is the closed bundle folder.

    Raises:
        InputError: if a file does not decode, a feature map has the wrong dimension, or no frame survives.
    """
    invalid, missing = [], []
    without_features = without_masks = 0
    for done, frame in enumerate(frames, start=1):
        if frame.T_world_cam is None or frame.depth is None:
            missing.append(frame.id)
        elif not is_rigid(frame.T_world_cam):
            invalid.append(frame.id)
        else:
            _add_source_frame(writer, frame, frame.T_world_cam, frame.depth)
            without_features += frame.features is None
            without_masks += frame.masks is None
        report(on_progress, done, len(frames))
    if writer.num_frames == 0:
        raise InputError(f"import: no usable frame among {len(frames)} (all lack a valid pose or depth)")
    for frame in skipped:
        if frame.T_world_cam is not None and is_rigid(frame.T_world_cam):
            writer.add_skipped_frame(frame.id, frame.T_world_cam)
    return ImportReport(
        bundle=writer.close(),
        frames_written=writer.num_frames,
        frames_skipped_invalid_pose=tuple(invalid),
        frames_skipped_missing=tuple(missing),
        frames_without_features=without_features,
        frames_without_masks=without_masks,
    )


def is_rigid(T: np.ndarray, tol: float = 1e-3) -> bool:
    """True for a finite (4, 4) rigid transform: orthonormal rotation with det 1, last row 0 0 0 1."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    rot = T[:3, :3]
    return bool(
        np.max(np.abs(rot.T @ rot - np.eye(3))) <= tol
        and abs(np.linalg.det(rot) - 1.0) <= tol
        and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6)
    )


def _add_source_frame(writer: BundleWriter, frame: SourceFrame, pose: np.ndarray, depth: Path) -> None:
    if frame.features is not None and writer.feature_dim is None:
        raise InputError(f"import: {frame.features}: a feature map in a bundle written without a feature dimension")
    depth_ok = png_info(depth) == (writer.camera.width, writer.camera.height, 16, 0)
    masks_ok = frame.masks is None or png_info(frame.masks)[2:] in ((8, 0), (16, 0))
    features_ok = frame.features is None or _npy_is_bundle_ready(frame.features, writer.feature_dim or 0)
    if depth_ok and masks_ok and features_ok:
        writer.add_frame_files(
            frame.id,
            pose,
            depth=depth,
            color=frame.color,
            features=frame.features,
            masks=frame.masks,
        )
        return
    # Something needs converting: write this frame from arrays (colour is still copied as a file).
    raw = _read_image(depth)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise InputError(f"import: {depth}: depth must be a 16-bit single-channel PNG")
    raw = resample_nearest(raw, (writer.camera.height, writer.camera.width))
    writer.add_frame(
        frame.id,
        pose,
        raw.astype(np.float64) / writer.depth_scale,  # round(v / s * s) == v: the values survive exactly
        color=frame.color,
        features=None if frame.features is None else _load_features(frame.features, writer.feature_dim or 0),
        masks=None if frame.masks is None else masks_to_ids(_read_image(frame.masks)),
    )


def resample_nearest(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:  # (h, w, ...) same dtype
    """Nearest-neighbour resampling with pixel centres: output (v, u) reads input (floor((v+.5)·H/h), ...).

    This is the lookup rule docs/scene_format.md §2.3 uses for feature maps, so resampled depth and intrinsics scaled by
    :meth:`Camera.scaled` stay consistent. (cv2's INTER_NEAREST reads floor(v·H/h), a quarter pixel off.)

    Args:
        image: ``(H, W)`` or ``(H, W, C)``.
        size: ``(h, w)`` of the output.
    """
    h_in, w_in = image.shape[:2]
    h, w = size
    if (h_in, w_in) == (h, w):
        return image
    rows = np.minimum(((np.arange(h) + 0.5) * h_in / h).astype(np.int64), h_in - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * w_in / w).astype(np.int64), w_in - 1)
    return image[rows[:, None], cols[None, :]]


def masks_to_ids(image: np.ndarray) -> np.ndarray:  # (Hm, Wm) int64
    """A mask image as ids: single channel as is; colour images get one id per colour, black = 0.

    Raises:
        InputError: if there are more than 65535 distinct colours.
    """
    if image.ndim == 2 or image.shape[2] < 3:  # grey, or grey + alpha
        return (image if image.ndim == 2 else image[:, :, 0]).astype(np.int64)
    rgb = image[:, :, :3].astype(np.int64)
    key = (rgb[:, :, 0] << 16) | (rgb[:, :, 1] << 8) | rgb[:, :, 2]
    colours, ids = np.unique(key, return_inverse=True)
    if colours[0] != 0:
        ids = ids + 1  # no black in the image: every colour is a mask
    if ids.max(initial=0) > MAX_PNG_VALUE:
        raise InputError(f"import: {len(colours)} mask colours, at most {MAX_PNG_VALUE} fit a 16-bit PNG")
    return ids.reshape(key.shape).astype(np.int64)


def png_info(path: Path) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from a PNG's IHDR chunk, without decoding it.

    Raises:
        InputError: if the file is not a PNG.
    """
    with Path(path).open("rb") as fh:
        head = fh.read(26)
    if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise InputError(f"import: {path}: not a PNG file")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    return width, height, head[24], head[25]


def npy_shape(path: Path) -> tuple[tuple[int, ...], np.dtype[Any], bool]:
    """(shape, dtype, fortran order) from a .npy header, without reading the data.

    Raises:
        InputError: if the file is not a .npy array.
    """
    try:
        with Path(path).open("rb") as fh:
            version = np.lib.format.read_magic(fh)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read(fh)
    except (ValueError, OSError) as exc:
        raise InputError(f"import: {path}: not a .npy file ({exc})") from exc
    return tuple(shape), dtype, bool(fortran)


def feature_dim_of(paths: list[Path], folder: Path) -> int:
    """D of the first feature map (header only); an import needs at least one map.

    Raises:
        InputError: if ``paths`` is empty or the first map is not ``(Hf, Wf, D)``.
    """
    if not paths:
        raise InputError(
            f"import: no feature maps in {folder} for the selected frames; a bundle needs at least one "
            "(Hf, Wf, D) .npy map"
        )
    shape, _, _ = npy_shape(paths[0])
    if len(shape) != 3 or shape[2] < 1:
        raise InputError(f"import: {paths[0]}: feature map of shape {shape}, expected (Hf, Wf, D)")
    return int(shape[2])


def read_matrix(path: Path) -> np.ndarray | None:  # (R, C) float64
    """A whitespace-separated text matrix (``-inf`` / ``nan`` allowed); None when missing or malformed."""
    try:
        return np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError):
        return None


def require_empty(dst: Path) -> None:
    """Refuse to import into a folder that already holds something (stale frames would mix in).

    Raises:
        InputError: if ``dst`` exists and is not an empty folder.
    """
    if dst.exists() and (not dst.is_dir() or any(dst.iterdir())):
        raise InputError(f"import: {dst} exists and is not an empty folder")


def _npy_is_bundle_ready(path: Path, dim: int) -> bool:
    shape, dtype, fortran = npy_shape(path)
    if len(shape) != 3 or shape[2] != dim:
        raise InputError(f"import: {path}: feature map of shape {shape}, expected (Hf, Wf, {dim})")
    return dtype in (np.float16, np.float32) and not fortran


def _load_features(path: Path, dim: int) -> np.ndarray:  # (Hf, Wf, D) float16/32, C order
    feat = np.load(path, allow_pickle=False)
    if feat.ndim != 3 or feat.shape[2] != dim or feat.dtype.kind != "f":
        raise InputError(f"import: {path}: feature map {feat.dtype} {feat.shape}, expected (Hf, Wf, {dim})")
    if feat.dtype not in (np.float16, np.float32):
        feat = feat.astype(np.float32)
    return np.ascontiguousarray(feat)


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"import: {path}: does not decode as an image")
    return image


def id_list(ids: tuple[str, ...], limit: int = 10) -> str:
    """The first ``limit`` ids joined by commas, then how many more."""
    shown = ", ".join(ids[:limit])
    return shown + (f" ... (+{len(ids) - limit})" if len(ids) > limit else "")


def write_import(
    dst: str | Path,
    frames: list[SourceFrame],
    *,
    name: str,
    camera: Camera,
    depth_scale: float,
    feature_dim: int,
    feature_space: str,
    geometry: str | Path | None = None,
    vocabulary: Vocabulary | None = None,
    ground_truth: str | Path | None = None,
    skipped: Sequence[SourceFrame] = (),
    on_progress: ProgressFn | None = None,
) -> ImportReport:
    """The end every importer shares: a bundle with optional geometry, vocabulary and ground truth, then frames.

    Ground truth (``.npz`` or ScanNet annotations, see :mod:`panogs_core.io.ground_truth`) is read and checked
    before anything is written; it brings ScanNet-20 as the vocabulary when it comes from ScanNet annotations and
    no vocabulary was given.

    Raises:
        InputError: for ground truth that is unreadable, inconsistent, or does not match the vocabulary or the
            geometry, and for any problem of the frames (see :func:`write_source_frames`).
    """
    gt = None
    if ground_truth is not None:
        vocabulary = vocabulary_for_ground_truth(ground_truth, vocabulary, feature_space=feature_space)
        vertices = None
        if geometry is not None:
            ply = read_ply_vertices(geometry)
            if {"x", "y", "z"} <= ply.keys():
                vertices = np.stack([ply[k] for k in "xyz"], axis=1)
        gt = load_ground_truth(ground_truth, vocabulary, vertices=vertices, vertices_name=f"geometry {geometry}")
    dst = Path(dst)
    with staged(dst) as stage:
        writer = BundleWriter(
            stage,
            name=name,
            camera=camera,
            depth_scale=depth_scale,
            feature_dim=feature_dim,
            feature_space=feature_space,
        )
        if geometry is not None:
            writer.write_geometry_file(geometry)
        if vocabulary is not None:
            writer.write_vocabulary(vocabulary)
        if gt is not None:
            writer.write_ground_truth(gt.semantic, gt.instance, gt.points)
        result = write_source_frames(writer, frames, skipped=skipped, on_progress=on_progress)
    return replace(result, bundle=dst)


@contextmanager
def staged(dst: Path) -> Iterator[Path]:
    """A staging folder ``.<dst>.partial-<pid>`` beside ``dst``: renamed to ``dst`` when the block ends, removed
    when it raises, so that an import that fails leaves nothing half-written at ``dst``. ``dst`` must be absent or
    an empty folder (:func:`require_empty`)."""
    stage = dst.parent / f".{dst.name}.partial-{os.getpid()}"
    if stage.exists():
        shutil.rmtree(stage)
    try:
        yield stage
        if dst.exists():
            dst.rmdir()  # empty: the staged bundle takes its place
        stage.rename(dst)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
