"""Import Record3D's "EXR + JPG" export or ``.r3d`` archive (an iPhone / iPad LiDAR capture) into a scene bundle.

Source layout::

    <src>/metadata.json     {"K": 9 numbers, column-major, of the colour camera at w x h; "w", "h";
                             "poses": per frame [qx, qy, qz, qw, tx, ty, tz] camera-to-world, ARKit axes}
                             (``metadata`` without the extension is accepted too)
    <src>/rgb/<n>.jpg       colour, e.g. 1920x1440 (larger than the depth)
    <src>/depth/<n>.exr     one float channel, metres, at the LiDAR's 256x192; 0 or non-finite = no depth
    <src>/conf/<n>.png      optional ARKit confidence per depth pixel: 0 low, 1 medium, 2 high

Frame ``n`` takes pose ``n``. ARKit poses use OpenGL camera axes (x right, y up, looking down -z) in a
gravity-aligned world with +Y up; they are turned into OpenCV axes (docs/conventions.md) by flipping the camera's
y and z. The bundle camera is the depth camera: ``K`` is scaled from the colour size to the depth size (same field
of view; the aspect ratios must agree), and the colour JPEG is copied as it is (the bundle resamples colour to
the camera size, docs/scene_format.md §1). Depth pixels whose confidence is below ``min_confidence`` are cleared.

An ``.r3d`` archive holds the same in other names (``rgbd/<n>.jpg``, LZFSE-compressed ``rgbd/<n>.depth`` float32
and ``rgbd/<n>.conf`` uint8, ``metadata``): :mod:`record3d_archive` unpacks it into this layout in a temporary
folder, and the ``pyliblzfse`` package decodes its depth.

EXR is read with the ``OpenEXR`` bindings (the format's reference library): OpenCV decodes EXR only when an
environment variable is set before its first use, which a library must not depend on, and a reader of our own
would cover only some of the compressions a capture app may write.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.importers.capture import (
    GL_TO_CV,
    Capture,
    CaptureFrame,
    CaptureReport,
    FrameSelection,
    MapSources,
    import_capture,
    quaternion_pose,
)
from panogs_core.io.importers.common import resample_nearest
from panogs_core.progress import ProgressFn
from panogs_core.types import Camera

logger = logging.getLogger(__name__)

RECORD3D_DEPTH_SCALE = 1000.0  # bundle PNG units per metre: millimetres reach 65 m, beyond the LiDAR's 5 m
ARKIT_UP = (0.0, 1.0, 0.0)  # ARKit's world is gravity-aligned with +Y up
DEPTH_SUFFIXES = (".exr", ".depth")  # the EXR + JPG export's, the .r3d archive's (LZFSE float32)


@dataclass(frozen=True, kw_only=True)
class Record3DOptions:
    """Settings of the Record3D import.

    Attributes:
        min_confidence: Depth pixels whose ARKit confidence (``conf/<n>.png``: 0 low, 1 medium, 2 high) is below
            this are cleared; 0 keeps all. Without confidence maps nothing is cleared.
        name: Scene name; the source folder's by default.
    """

    min_confidence: int = 1  # ours: low-confidence LiDAR depth is where edges and dark surfaces smear
    name: str | None = None
    selection: FrameSelection = field(default_factory=FrameSelection)
    maps: MapSources = field(default_factory=MapSources)

    def __post_init__(self) -> None:
        if self.min_confidence not in (0, 1, 2):
            raise InputError(f"import record3d: min_confidence must be 0, 1 or 2, got {self.min_confidence}")


def import_record3d(
    src: str | Path,
    dst: str | Path,
    options: Record3DOptions | None = None,
    *,
    on_progress: ProgressFn | None = None,
) -> CaptureReport:
    """Convert a Record3D EXR + JPG export folder into a bundle at ``dst`` (module docstring).

    Args:
        src: The export folder (``metadata.json``, ``rgb/``, ``depth/``, optional ``conf/``).
        dst: Bundle folder to create (must not exist or be empty).
        options: Confidence threshold, name, frame selection and 2D maps.
        on_progress: Called with ``(done, total)`` per frame written.

    Returns:
        The report: frames kept and dropped, depth range, size, gravity up (+Y), the next command.

    Raises:
        InputError: for a missing or malformed ``metadata.json``, no depth images, colour and depth of different
            aspect ratios, no usable frame, no 2D maps without placeholder maps, or ``dst`` not empty.
    """
    opts = options or Record3DOptions()
    src = Path(src)
    if src.is_file() and src.suffix.lower() == ".r3d":
        from panogs_core.io.importers.record3d_archive import unpacked_r3d

        with unpacked_r3d(src) as folder:
            named = opts if opts.name else replace(opts, name=src.stem)
            return import_record3d(folder, dst, named, on_progress=on_progress)
    meta_path, meta = _read_metadata(src)
    depths = sorted(
        ((int(p.stem), p) for p in (src / "depth").iterdir() if p.stem.isdigit() and p.suffix in DEPTH_SUFFIXES)
        if (src / "depth").is_dir()
        else (),
        key=lambda item: item[0],
    )
    if not depths:
        raise InputError(f"import record3d: {src / 'depth'} has no <n>.exr depth images")
    camera = _depth_camera(meta_path, meta, depths[0][1])
    poses = meta["poses"]
    frames, no_pose = [], []
    for n, depth in depths:
        if n >= len(poses):
            no_pose.append(f"{n} ({depth.name}: {meta_path.name} has {len(poses)} poses)")
            continue
        conf = next((c for c in (src / "conf" / f"{n}.png", src / "conf" / f"{n}.conf") if c.is_file()), src)
        frames.append(
            CaptureFrame(
                id=f"{n:06d}",
                stem=str(n),
                T_world_cam=_pose(poses[n]),
                depth=depth,
                color=src / "rgb" / f"{n}.jpg",
                extra=(conf,) if opts.min_confidence > 0 and conf.is_file() else (),
            )
        )

    # Poses whose frame has no depth image (a user who pruned the export, as real captures show): named, not silent.
    present = {n for n, _ in depths}
    no_depth = [
        f"{n:06d} (pose {n} of {meta_path.name} has no depth image)" for n in range(len(poses)) if n not in present
    ]

    def read(frame: CaptureFrame) -> np.ndarray:
        return _read_depth(frame, camera, meta, opts.min_confidence)

    capture = Capture(
        source="record3d",
        name=opts.name or src.name,
        camera=camera,
        frames=frames,
        read_depth=read,
        depth_scale=RECORD3D_DEPTH_SCALE,
        gravity_up=ARKIT_UP,
        gravity_note="ARKit's gravity-aligned world",
        dropped={reason: ids for reason, ids in (("no pose in metadata", no_pose), ("missing file", no_depth)) if ids},
    )
    result = import_capture(dst, capture, opts.selection, opts.maps, on_progress=on_progress)
    logger.info("import record3d: %s", result.summary())
    return result


def read_exr_depth(path: Path) -> np.ndarray:  # (H, W) float32
    """The single float channel of an EXR depth image.

    Raises:
        InputError: naming the file, if it does not decode (truncated, not EXR) or has no float channel.
    """
    import OpenEXR  # the reference library's bindings; imported here so other importers do not need it

    try:
        with OpenEXR.File(str(path)) as exr:
            channels = exr.channels()
            names = [n for n in ("Z", "R", "Y", "depth") if n in channels] or sorted(channels)
            if not names:
                raise InputError(f"import record3d: {path}: an EXR without channels")
            pixels = np.asarray(channels[names[0]].pixels)
    except InputError:
        raise
    except Exception as exc:  # the bindings raise RuntimeError / ValueError / OSError for damaged files
        raise InputError(f"import record3d: {path}: does not decode as EXR ({exc})") from exc
    if pixels.ndim == 3:
        pixels = pixels[:, :, 0]
    if pixels.ndim != 2 or pixels.dtype.kind != "f":
        raise InputError(f"import record3d: {path}: expected one float channel, got {pixels.dtype} {pixels.shape}")
    return pixels.astype(np.float32)


def read_lzfse(path: Path, dtype: type[np.generic], shape: tuple[int, int]) -> np.ndarray:  # (H, W)
    """An LZFSE-compressed raw image of the ``.r3d`` archive (``.depth`` float32 metres, ``.conf`` uint8).

    Raises:
        InputError: naming the file, if it does not decompress or holds another number of pixels.
    """
    try:
        import liblzfse  # the pyliblzfse package; only .r3d archives need it
    except ImportError as exc:
        raise InputError("import record3d: .r3d archives need the pyliblzfse package (pip install pyliblzfse)") from exc
    try:
        raw = liblzfse.decompress(path.read_bytes())
    except (liblzfse.error, OSError) as exc:
        raise InputError(f"import record3d: {path}: does not decompress as LZFSE ({exc})") from exc
    values = np.frombuffer(raw, dtype=dtype)
    if values.size != shape[0] * shape[1]:
        raise InputError(f"import record3d: {path}: {values.size} values, expected {shape[1]}x{shape[0]}")
    return values.reshape(shape)


def _depth_shape(meta: dict[str, Any], path: Path) -> tuple[int, int]:
    """(height, width) of an archive's depth: ``dh`` / ``dw`` of the metadata, else from the value count and the
    colour's aspect ratio."""
    if "dh" in meta and "dw" in meta:
        return int(meta["dh"]), int(meta["dw"])
    import liblzfse

    count = len(liblzfse.decompress(path.read_bytes())) // 4
    height = round(float(np.sqrt(count * int(meta["h"]) / int(meta["w"]))))
    return height, count // max(height, 1)


def read_depth_file(path: Path, meta: dict[str, Any]) -> np.ndarray:  # (H, W) float32 metres
    """A depth image of the export (``.exr``) or of the archive (``.depth``)."""
    if path.suffix == ".depth":
        try:
            shape = _depth_shape(meta, path)
        except Exception as exc:  # the decoder's own error type, or a malformed size
            raise InputError(f"import record3d: {path}: does not decompress as LZFSE ({exc})") from exc
        return read_lzfse(path, np.float32, shape).astype(np.float32)
    return read_exr_depth(path)


def _read_depth(frame: CaptureFrame, camera: Camera, meta: dict[str, Any], min_confidence: int) -> np.ndarray:
    depth = read_depth_file(frame.depth, meta)
    if depth.shape != (camera.height, camera.width):
        raise InputError(
            f"import record3d: {frame.depth}: {depth.shape[1]}x{depth.shape[0]}, expected {camera.width}x"
            f"{camera.height} like the first depth image"
        )
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    if frame.extra:
        path = frame.extra[0]
        conf = read_lzfse(path, np.uint8, depth.shape) if path.suffix == ".conf" else cv2.imread(str(path), -1)
        if conf is None or conf.ndim != 2:
            raise InputError(f"import record3d: {frame.extra[0]}: not a single-channel confidence image")
        conf = resample_nearest(conf, depth.shape)
        depth[conf < min_confidence] = 0.0
    return depth


def _pose(row: object) -> np.ndarray:  # (4, 4) camera-to-world, OpenCV axes; NaN when malformed
    try:
        values = np.asarray(row, dtype=np.float64) if isinstance(row, list) and len(row) == 7 else np.full(7, np.nan)
    except (TypeError, ValueError):
        values = np.full(7, np.nan)
    return quaternion_pose(values[:4], values[4:]) @ GL_TO_CV


def _read_metadata(src: Path) -> tuple[Path, dict[str, Any]]:
    path = next((p for p in (src / "metadata.json", src / "metadata") if p.is_file()), src / "metadata.json")
    if not path.is_file():
        raise InputError(f"import record3d: {path} is missing (Record3D's EXR + JPG export writes it)")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
        K, w, h, poses = meta["K"], int(meta["w"]), int(meta["h"]), meta["poses"]
        ok = isinstance(K, list) and len(K) == 9 and isinstance(poses, list) and w > 0 and h > 0
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"import record3d: {path}: expected K (9 numbers), w, h and poses ({exc})") from exc
    if not ok:
        raise InputError(f"import record3d: {path}: expected K (9 numbers), w, h and a list of poses")
    return path, meta


def _depth_camera(meta_path: Path, meta: dict[str, Any], first_depth: Path) -> Camera:
    K = np.asarray(meta["K"], dtype=np.float64).reshape(3, 3).T  # stored column-major
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"import record3d: {meta_path}: K is not a pinhole matrix: {meta['K']}")
    width, height = int(meta["w"]), int(meta["h"])
    colour = Camera(width=width, height=height, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    dh, dw = read_depth_file(first_depth, meta).shape
    if abs(dw / dh - width / height) > 0.01 * width / height:
        raise InputError(
            f"import record3d: colour {width}x{height} ({meta_path.name}) and depth {dw}x{dh} ({first_depth.name}) "
            "have different aspect ratios; the depth must cover the colour's field of view"
        )
    return colour.scaled(dw, dh)
