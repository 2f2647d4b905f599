"""Import a nerfstudio data folder (``transforms.json``, as ``ns-process-data`` writes it) into a scene bundle.

Source layout::

    <src>/transforms.json   {"fl_x", "fl_y", "cx", "cy", "w", "h", "camera_model", "k1", "k2", "k3", "k4",
                             "p1", "p2" at the top level or per frame; "frames": [{"file_path",
                             "transform_matrix", "depth_file_path", ...}], "ply_file_path" optional}
    <src>/images/...        colour, paths relative to transforms.json's folder
    <src>/depth/...         16-bit PNG, ``depth_unit`` metres per value (millimetres by default, nerfstudio's
                            ``depth_unit_scale_factor``), 0 = unknown; any size with the colour's aspect ratio

``transform_matrix`` is camera-to-world in OpenGL camera axes (x right, y up, looking down -z); the bundle's
OpenCV axes are reached by flipping the camera's y and z. The bundle camera is the depth camera: the intrinsics
are scaled from ``w`` x ``h`` to the depth images' size. Frames whose own intrinsics differ from the first
kept frame's are dropped (a bundle has one camera). ``ply_file_path`` becomes ``geometry.ply`` (it lives in the
same world as the poses); without it the primitives come from the depth (TSDF).

Distortion is refused rather than undistorted: the captures that carry depth in this layout (Polycam, Record3D,
ARKit-based apps) are already undistorted (``PINHOLE``, zero coefficients), while distorted ones come from COLMAP
on plain video, which has no depth anyway; undistorting depth would also mix neighbouring surfaces at edges.
Zero coefficients are accepted. ``mask_path`` (nerfstudio's pixels-to-ignore masks) is not instance masks and is
ignored, as are ``applied_transform`` and ``applied_scale`` (the poses in the file are already in its world).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
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
)
from panogs_core.io.importers.common import png_info, resample_nearest
from panogs_core.progress import ProgressFn
from panogs_core.types import Camera

logger = logging.getLogger(__name__)

_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
NO_DEPTH_HINT = (
    "panogs needs depth. nerfstudio writes depth_file_path for phone LiDAR captures: for Polycam run "
    "`ns-process-data polycam --data CAPTURE.zip --output-dir OUT --use-depth`; a Record3D EXR + JPG export "
    "imports directly with `panogs import record3d`"
)


@dataclass(frozen=True, kw_only=True)
class NerfstudioOptions:
    """Settings of the nerfstudio import.

    Attributes:
        depth_unit: Metres per depth PNG value (nerfstudio's ``depth_unit_scale_factor``; 0.001 = millimetres).
        use_ply: Copy ``ply_file_path`` as ``geometry.ply`` when the file names one.
        name: Scene name; the source folder's by default.
    """

    depth_unit: float = 0.001  # m per PNG value; nerfstudio's default
    use_ply: bool = True
    name: str | None = None
    selection: FrameSelection = field(default_factory=FrameSelection)
    maps: MapSources = field(default_factory=MapSources)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.depth_unit) and 0 < self.depth_unit <= 1):
            raise InputError(f"import nerfstudio: depth_unit must be in (0, 1] m per value, got {self.depth_unit}")


def import_nerfstudio(
    src: str | Path,
    dst: str | Path,
    options: NerfstudioOptions | None = None,
    *,
    on_progress: ProgressFn | None = None,
) -> CaptureReport:
    """Convert a nerfstudio data folder into a bundle at ``dst`` (module docstring).

    Args:
        src: The folder holding ``transforms.json`` (or the ``transforms.json`` file itself).
        dst: Bundle folder to create (must not exist or be empty).
        options: Depth unit, PLY use, name, frame selection and 2D maps.
        on_progress: Called with ``(done, total)`` per frame written.

    Raises:
        InputError: for a missing or malformed ``transforms.json``, no depth (with how to get it), distortion or
            a non-pinhole camera model, no usable frame, no 2D maps without placeholder maps, or ``dst`` not empty.
    """
    opts = options or NerfstudioOptions()
    path = Path(src)
    path = path if path.is_file() else path / "transforms.json"
    doc = _read_transforms(path)
    root = path.parent
    entries = doc["frames"]
    with_depth = [i for i, e in enumerate(entries) if isinstance(e, dict) and e.get("depth_file_path")]
    if not with_depth:
        raise InputError(f"import nerfstudio: {path}: no frame has a depth_file_path. {NO_DEPTH_HINT}")
    depth_size = _first_depth_size(root, entries, with_depth)
    reference = _intrinsics(doc, entries[with_depth[0]], path)
    camera = _camera(reference, depth_size, path)
    frames: list[CaptureFrame] = []
    dropped: dict[str, list[str]] = {}
    for i, entry in enumerate(entries):
        label = f"{i:06d}"
        if not isinstance(entry, dict) or not entry.get("depth_file_path"):
            dropped.setdefault("no depth_file_path", []).append(label)
        elif _intrinsics(doc, entry, path) != reference:
            dropped.setdefault("intrinsics differ from the first frame's", []).append(label)
        else:
            frames.append(_frame(root, i, entry))

    def read(frame: CaptureFrame) -> np.ndarray:
        return _read_depth(frame.depth, camera, opts.depth_unit)

    ply = doc.get("ply_file_path") if opts.use_ply else None
    capture = Capture(
        source="nerfstudio",
        name=opts.name or root.name,
        camera=camera,
        frames=frames,
        read_depth=read,
        depth_scale=1.0 / opts.depth_unit,
        geometry=_ply(root, ply, path) if ply else None,
        gravity_up=(0.0, 0.0, 1.0),
        gravity_note="usually +Z in data ns-process-data made; transforms.json does not record it",
        dropped=dropped,
    )
    result = import_capture(dst, capture, opts.selection, opts.maps, on_progress=on_progress)
    logger.info("import nerfstudio: %s", result.summary())
    return result


def _read_transforms(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise InputError(f"import nerfstudio: {path} is missing (ns-process-data writes it)")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, OSError) as exc:
        raise InputError(f"import nerfstudio: {path}: not JSON ({exc})") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise InputError(f"import nerfstudio: {path}: expected an object with a non-empty 'frames' list")
    return doc


def _intrinsics(doc: dict[str, Any], entry: Any, path: Path) -> tuple[float, ...]:
    """(fl_x, fl_y, cx, cy, w, h) of a frame (its own keys over the file's).

    Raises:
        InputError: if one is missing, the camera model is not a pinhole, or a distortion coefficient is not 0.
    """
    merged = {**doc, **(entry if isinstance(entry, dict) else {})}
    model = str(merged.get("camera_model", "OPENCV"))
    if model not in _PINHOLE_MODELS:
        raise InputError(
            f"import nerfstudio: {path}: camera_model {model}; only pinhole cameras ({', '.join(_PINHOLE_MODELS)}) "
            "are read. Undistort the images first (e.g. COLMAP's image_undistorter)"
        )
    bent = {k: merged[k] for k in _DISTORTION if float(merged.get(k, 0.0) or 0.0) != 0.0}
    if bent:
        raise InputError(
            f"import nerfstudio: {path}: distortion coefficients {bent}; panogs reads undistorted pinhole images "
            "and depth only (undistorting depth mixes surfaces at edges). Undistort the colour and depth first"
        )
    try:
        values = tuple(float(merged[k]) for k in _INTRINSICS)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"import nerfstudio: {path}: intrinsics {', '.join(_INTRINSICS)} needed ({exc})") from exc
    if not all(np.isfinite(values)) or min(values) <= 0:
        raise InputError(f"import nerfstudio: {path}: intrinsics must be positive numbers, got {values}")
    return values


def _camera(intrinsics: tuple[float, ...], depth_size: tuple[int, int], path: Path) -> Camera:
    fx, fy, cx, cy, w, h = intrinsics
    width, height = depth_size
    if abs(width / height - w / h) > 0.01 * w / h:
        raise InputError(
            f"import nerfstudio: {path}: images {w:g}x{h:g} and depth {width}x{height} have different aspect ratios"
        )
    return Camera(width=int(w), height=int(h), fx=fx, fy=fy, cx=cx, cy=cy).scaled(width, height)


def _first_depth_size(root: Path, entries: list[Any], with_depth: list[int]) -> tuple[int, int]:
    for i in with_depth:
        depth = root / str(entries[i]["depth_file_path"])
        if depth.is_file():
            width, height, _, _ = png_info(depth)
            return width, height
    first = root / str(entries[with_depth[0]]["depth_file_path"])
    raise InputError(f"import nerfstudio: none of the depth_file_path files exists (first: {first})")


def _frame(root: Path, index: int, entry: dict[str, Any]) -> CaptureFrame:
    try:
        T_gl = np.asarray(entry.get("transform_matrix"), dtype=np.float64)
    except (TypeError, ValueError):
        T_gl = np.full((4, 4), np.nan)
    if T_gl.shape == (3, 4):
        T_gl = np.vstack([T_gl, [0.0, 0.0, 0.0, 1.0]])
    pose = T_gl @ GL_TO_CV if T_gl.shape == (4, 4) else np.full((4, 4), np.nan)
    color = entry.get("file_path")
    return CaptureFrame(
        id=f"{index:06d}",
        stem=Path(str(color)).stem if color else f"{index:06d}",
        T_world_cam=pose,
        depth=root / str(entry["depth_file_path"]),
        color=root / str(color) if color else None,
    )


def _ply(root: Path, rel: str, path: Path) -> Path:
    ply = root / rel
    if not ply.is_file():
        raise InputError(f"import nerfstudio: {path}: ply_file_path {ply} does not exist")
    return ply


def _read_depth(path: Path, camera: Camera, unit: float) -> np.ndarray:  # (H, W) metres
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"import nerfstudio: {path}: does not decode as an image")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise InputError(f"import nerfstudio: {path}: {raw.dtype} {raw.shape}, expected a 16-bit single-channel PNG")
    if raw.shape != (camera.height, camera.width):
        raw = resample_nearest(raw, (camera.height, camera.width))  # same field of view, another size
    return raw.astype(np.float64) * unit
