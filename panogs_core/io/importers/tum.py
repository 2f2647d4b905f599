"""Import a sequence in the TUM RGB-D layout (the TUM benchmark's, and what many SLAM tools write) into a bundle.

Source layout::

    <src>/rgb.txt           lines "timestamp path" (``#`` comments), path relative to <src>: colour PNGs
    <src>/depth.txt         the same for the depth PNGs: uint16, metres = value / 5000, 0 = no depth
    <src>/groundtruth.txt   lines "timestamp tx ty tz qx qy qz qw": camera-to-world of the optical centre,
                            OpenCV camera axes, metres

The three streams are not synchronous. Each depth image takes the colour image and the pose nearest to it in
time, when they lie within ``max_time_difference`` (0.02 s, the benchmark's ``associate.py``); a depth image
without either is dropped and counted by reason. The bundle camera is the depth camera: the depth images are
registered to the colour camera by the Kinect driver, so the colour intrinsics apply (the dataset's page), and
they come from a text file ``fx fy cx cy`` or from a named Freiburg camera. Freiburg 1 and 2 colour images carry
lens distortion (the published d0..d4), which the benchmark's own tools ignore, and so does this importer.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.importers.capture import (
    Capture,
    CaptureFrame,
    CaptureReport,
    FrameSelection,
    MapSources,
    import_capture,
    quaternion_pose,
)
from panogs_core.io.importers.common import png_info
from panogs_core.progress import ProgressFn
from panogs_core.types import Camera

logger = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0  # PNG value per metre (the dataset's file-format page)
# The dataset's published colour-camera calibrations (fx, fy, cx, cy) at 640x480; the same values appear in
# ORB-SLAM2's TUM1/2/3.yaml.
FREIBURG_CAMERAS: dict[str, tuple[float, float, float, float]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
FreiburgCamera = Literal["freiburg1", "freiburg2", "freiburg3"]


@dataclass(frozen=True, kw_only=True)
class TumOptions:
    """Settings of the TUM RGB-D import.

    Attributes:
        intrinsics: A text file ``fx fy cx cy`` of the depth camera at the depth images' size.
        camera: A Freiburg camera by name, instead of ``intrinsics``.
        max_time_difference: Seconds; a depth image takes the nearest colour image and pose within this.
        depth_scale: Depth PNG value per metre.
        name: Scene name; the source folder's by default.
    """

    intrinsics: Path | None = None
    camera: FreiburgCamera | None = None
    max_time_difference: float = 0.02  # s; the benchmark's associate.py default
    depth_scale: float = TUM_DEPTH_SCALE
    name: str | None = None
    selection: FrameSelection = field(default_factory=FrameSelection)
    maps: MapSources = field(default_factory=MapSources)

    def __post_init__(self) -> None:
        if self.camera is not None and self.camera not in FREIBURG_CAMERAS:
            raise InputError(f"import tum: camera must be one of {', '.join(FREIBURG_CAMERAS)}, got {self.camera!r}")
        if not self.max_time_difference > 0:
            raise InputError(f"import tum: max_time_difference must be > 0 s, got {self.max_time_difference}")
        if not (np.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise InputError(f"import tum: depth_scale must be > 0, got {self.depth_scale}")


def import_tum(
    src: str | Path,
    dst: str | Path,
    options: TumOptions | None = None,
    *,
    on_progress: ProgressFn | None = None,
) -> CaptureReport:
    """Convert a TUM RGB-D sequence folder into a bundle at ``dst`` (module docstring).

    Args:
        src: The sequence folder (``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` and the images they name).
        dst: Bundle folder to create (must not exist or be empty).
        options: Intrinsics, time tolerance, depth scale, name, frame selection and 2D maps.
        on_progress: Called with ``(done, total)`` per frame written.

    Raises:
        InputError: without intrinsics (neither file nor camera), for a missing or malformed list file, an
            empty association, no usable frame, no 2D maps without placeholder maps, or ``dst`` not empty.
    """
    opts = options or TumOptions()
    src = Path(src)
    if (opts.intrinsics is None) == (opts.camera is None):
        raise InputError(
            "import tum: give the depth camera's intrinsics, exactly one of: a file 'fx fy cx cy' (--intrinsics "
            "FILE) or a Freiburg camera (--camera freiburg1|freiburg2|freiburg3, the dataset's published values; "
            "the sequence name says which, e.g. rgbd_dataset_freiburg1_desk)"
        )
    depth_list = _read_list(src / "depth.txt")
    rgb_list = _read_list(src / "rgb.txt")
    poses = _read_groundtruth(src / "groundtruth.txt")
    if not depth_list:
        raise InputError(f"import tum: {src / 'depth.txt'} lists no depth image")
    width, height, _, _ = _first_png_size(src, depth_list)
    camera = _camera(opts, width, height)
    frames, dropped = _associate(src, depth_list, rgb_list, poses, opts.max_time_difference)
    if not frames:
        raise InputError(
            f"import tum: no depth image of {src / 'depth.txt'} has a colour image ({src / 'rgb.txt'}) and a pose "
            f"({src / 'groundtruth.txt'}) within {opts.max_time_difference} s: "
            + "; ".join(f"{len(ids)} {reason}" for reason, ids in dropped.items())
        )

    def read(frame: CaptureFrame) -> np.ndarray:
        return _read_depth(frame.depth, camera, opts.depth_scale)

    capture = Capture(
        source="tum",
        name=opts.name or src.name,
        camera=camera,
        frames=frames,
        read_depth=read,
        depth_scale=opts.depth_scale,
        gravity_note="the motion-capture frame of the sequence is not documented as gravity-aligned",
        dropped=dropped,
    )
    result = import_capture(dst, capture, opts.selection, opts.maps, on_progress=on_progress)
    logger.info("import tum: %s", result.summary())
    return result


def associate(query: np.ndarray, reference: np.ndarray, tolerance: float) -> np.ndarray:  # (Q,) int64, -1 = none
    """For each query time, the index of the nearest reference time within ``tolerance`` seconds, else -1.

    Example:
        >>> associate(np.array([1.0, 2.0, 3.5]), np.array([0.99, 2.05, 3.49]), 0.02).tolist()
        [0, -1, 2]
    """
    if reference.size == 0:
        return np.full(query.shape, -1, np.int64)
    order = np.argsort(reference)
    ref = reference[order]
    right = np.clip(np.searchsorted(ref, query), 0, len(ref) - 1)
    left = np.clip(right - 1, 0, len(ref) - 1)
    nearest = np.where(np.abs(ref[left] - query) <= np.abs(ref[right] - query), left, right)
    found = np.abs(ref[nearest] - query) <= tolerance
    return np.where(found, order[nearest], -1).astype(np.int64)


def _associate(
    src: Path,
    depth_list: list[tuple[float, str]],
    rgb_list: list[tuple[float, str]],
    poses: tuple[np.ndarray, np.ndarray],
    tolerance: float,
) -> tuple[list[CaptureFrame], dict[str, list[str]]]:
    depth_t = np.array([t for t, _ in depth_list])
    rgb_of = associate(depth_t, np.array([t for t, _ in rgb_list]), tolerance)
    pose_of = associate(depth_t, poses[0], tolerance)
    frames: list[CaptureFrame] = []
    dropped: dict[str, list[str]] = {}
    for i, (stamp, rel) in enumerate(depth_list):
        label = f"{i:06d} (depth {stamp:.6f})"
        if rgb_of[i] < 0:
            dropped.setdefault(f"no colour image within {tolerance} s", []).append(label)
        elif pose_of[i] < 0:
            dropped.setdefault(f"no pose within {tolerance} s", []).append(label)
        else:
            row = poses[1][pose_of[i]]
            frames.append(
                CaptureFrame(
                    id=f"{i:06d}",
                    stem=Path(rel).stem,
                    T_world_cam=quaternion_pose(row[3:7], row[:3]),
                    depth=src / rel,
                    color=src / rgb_list[rgb_of[i]][1],
                )
            )
    return frames, dropped


def _read_list(path: Path) -> list[tuple[float, str]]:
    """``timestamp path`` lines, sorted by time.

    Raises:
        InputError: if the file is missing or a line is not ``<number> <path>``.
    """
    if not path.is_file():
        raise InputError(f"import tum: {path} is missing (lines 'timestamp path')")
    rows = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            rows.append((float(parts[0]), parts[1]))
        except (ValueError, IndexError) as exc:
            raise InputError(f"import tum: {path} line {number}: expected 'timestamp path', got {line!r}") from exc
    return sorted(rows)


def _read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:  # (P,) times, (P, 7) tx ty tz qx qy qz qw
    """Malformed lines become NaN poses, so that a frame that takes one is reported as an invalid pose."""
    if not path.is_file():
        raise InputError(f"import tum: {path} is missing (lines 'timestamp tx ty tz qx qy qz qw')")
    times, rows = [], []
    for line in path.read_text(encoding="utf-8").splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            stamp = float(parts[0])
        except ValueError:
            continue  # no time: it cannot be associated with anything
        try:
            values = [float(v) for v in parts[1:8]] if len(parts) == 8 else [np.nan] * 7
        except ValueError:
            values = [np.nan] * 7
        times.append(stamp)
        rows.append(values)
    return np.array(times, dtype=np.float64), np.array(rows, dtype=np.float64).reshape(-1, 7)


def _first_png_size(src: Path, depth_list: list[tuple[float, str]]) -> tuple[int, int, int, int]:
    for _, rel in depth_list:
        if (src / rel).is_file():
            return png_info(src / rel)
    raise InputError(f"import tum: none of the depth images listed in {src / 'depth.txt'} exists")


def _camera(opts: TumOptions, width: int, height: int) -> Camera:
    if opts.camera is not None:
        fx, fy, cx, cy = FREIBURG_CAMERAS[opts.camera]
        return Camera(width=640, height=480, fx=fx, fy=fy, cx=cx, cy=cy).scaled(width, height)
    path = Path(opts.intrinsics)  # type: ignore[arg-type]
    try:
        values = [float(v) for v in path.read_text(encoding="utf-8").split()]
    except (OSError, ValueError) as exc:
        raise InputError(f"import tum: {path}: expected a text file 'fx fy cx cy' ({exc})") from exc
    if len(values) != 4 or not all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
        raise InputError(f"import tum: {path}: expected four numbers 'fx fy cx cy', got {values}")
    return Camera(width=width, height=height, fx=values[0], fy=values[1], cx=values[2], cy=values[3])


def _read_depth(path: Path, camera: Camera, scale: float) -> np.ndarray:  # (H, W) metres
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"import tum: {path}: does not decode as an image")
    if raw.ndim != 2 or raw.dtype != np.uint16 or raw.shape != (camera.height, camera.width):
        raise InputError(
            f"import tum: {path}: {raw.dtype} {raw.shape}, expected a {camera.width}x{camera.height} 16-bit PNG"
        )
    return raw.astype(np.float64) / scale
