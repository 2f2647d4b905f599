"""What the capture importers (nerfstudio, Record3D, TUM RGB-D) share: frame selection, the 2D maps' folders,
the write into a staging folder that becomes ``dst`` only when the bundle is complete, and the import report.

A source module parses its layout into :class:`CaptureFrame` rows (pose already converted to camera-to-world in
OpenCV axes, docs/conventions.md) and a depth reader, then calls :func:`import_capture`, which

1. drops frames whose files are missing or whose pose is not a finite rotation + translation (named in the report),
2. keeps every ``stride``-th of the rest, then the key frames by motion (a frame is kept when it moved more than
   ``min_translation`` or turned more than ``min_rotation`` since the last kept one), then at most ``max_frames``
   spread evenly over what is left,
3. writes the bundle into ``.<dst>.partial-<pid>`` beside ``dst`` and renames it to ``dst`` at the end; any error
   removes the staging folder, so nothing half-written is ever left at ``dst``.

Frames whose depth does not decode are dropped and named like the others; an import fails only when no frame is
left. The capture's gravity direction, when the source knows it, becomes ``scene.json``'s ``up``; the valid frames
that the stride, the motion rule or ``max_frames`` left out are kept by their pose only (``skipped_frames``,
docs/scene_format.md §2.6), so that a run can be rendered from any frame of the capture.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.io.importers.common import feature_dim_of, id_list, is_rigid, masks_to_ids, require_empty, staged
from panogs_core.io.importers.sevenscenes import PLACEHOLDER_DIM, PLACEHOLDER_SPACE, placeholder_vocabulary
from panogs_core.progress import ProgressFn, report
from panogs_core.types import Camera, Vocabulary

# OpenGL camera axes (x right, y up, looking down -z: nerfstudio, ARKit) to OpenCV's (x right, y down, z forward):
# T_world_cv = T_world_gl @ GL_TO_CV flips the camera's y and z axes.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
_DEPTH_SAMPLE = 4096  # depth values kept per frame for the report's depth range (a strided sample, not all pixels)


@dataclass(frozen=True, kw_only=True)
class FrameSelection:
    """Which of a capture's frames become bundle frames.

    Attributes:
        stride: Keep every ``stride``-th frame of the capture (after dropping invalid ones).
        min_translation: Metres; with ``min_rotation``, a frame is kept only when it moved more than this or
            turned more than ``min_rotation`` since the last kept frame. 0 and 0 keep every frame.
        min_rotation: Degrees; see ``min_translation``.
        max_frames: At most this many frames, spread evenly over the selected ones; None for no cap.
    """

    stride: int = 1
    min_translation: float = 0.0  # m; ours: off by default (a capture's own frame rate decides)
    min_rotation: float = 0.0  # degrees; ours: off by default
    max_frames: int | None = None

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise InputError(f"import: stride must be >= 1, got {self.stride}")
        if not (self.min_translation >= 0 and self.min_rotation >= 0):
            raise InputError(
                f"import: min_translation and min_rotation must be >= 0, got {self.min_translation}, "
                f"{self.min_rotation}"
            )
        if self.max_frames is not None and self.max_frames < 1:
            raise InputError(f"import: max_frames must be >= 1 or None, got {self.max_frames}")


@dataclass(frozen=True, kw_only=True)
class MapSources:
    """Where the bundle's 2D maps come from.

    Attributes:
        features: Folder of per-frame ``(Hf, Wf, D)`` ``.npy`` feature maps named by the frame's stem or id.
        masks: Folder of per-frame instance-id ``.png`` masks named the same way.
        placeholder_maps: Without feature maps: a constant feature map and one-segment mask on the first frame
            (as the 7-Scenes importer), enough to fit and render, never meaningful labels. Without feature maps
            and without this, the bundle has no maps of that kind and ``panogs run --masks-model ...
            --features-model ...`` computes them from the colour frames (docs/method.md §17).
        feature_space: ``features.space`` of the feature maps.
        vocabulary: Label set to write (not with placeholder maps).
    """

    features: Path | None = None
    masks: Path | None = None
    placeholder_maps: bool = False
    feature_space: str = "clip-vit-b32"
    vocabulary: Vocabulary | None = None


@dataclass(frozen=True)
class CaptureFrame:
    """One frame of a capture, parsed. ``stem`` names its maps in the feature and mask folders."""

    id: str
    stem: str
    T_world_cam: np.ndarray  # (4, 4) camera-to-world, OpenCV axes, metres; may be invalid (checked here)
    depth: Path
    color: Path | None = None
    extra: tuple[Path, ...] = ()  # other files the frame needs (a confidence map); missing ones drop it


DepthReader = Callable[[CaptureFrame], np.ndarray]  # (H, W) float metres at the camera size; raises InputError


@dataclass(frozen=True)
class Capture:
    """A parsed capture, ready to write.

    Attributes:
        source: The source's name, for messages (``nerfstudio``, ``record3d``, ``tum``).
        name: Scene name.
        camera: The bundle camera (the depth images').
        frames: Every frame found, in capture order.
        read_depth: Reads one frame's depth in metres at the camera size.
        depth_scale: The bundle's depth PNG value per metre.
        geometry: A PLY of the capture to copy as ``geometry.ply``; None leaves the primitives to the TSDF path.
        gravity_up: The world's up direction when the source knows it, else None.
        gravity_note: Where ``gravity_up`` comes from.
        dropped: Frames the parser already dropped, by reason (e.g. no pose within the time tolerance).
    """

    source: str
    name: str
    camera: Camera
    frames: list[CaptureFrame]
    read_depth: DepthReader
    depth_scale: float = 1000.0
    geometry: Path | None = None
    gravity_up: tuple[float, float, float] | None = None
    gravity_note: str = "the source does not record it"
    dropped: dict[str, list[str]] = field(default_factory=dict)


@dataclass(frozen=True)
class CaptureReport:
    """What a capture import wrote, what it dropped and why.

    Attributes:
        bundle: The bundle folder.
        frames_source: Frames in the capture.
        frames_written: Frames in ``scene.json``.
        dropped: ``(reason, frame names)`` for every reason a frame was left out.
        not_selected: Valid frames left out by the stride, the motion rule or ``max_frames``.
        depth_range: (min, median, max) metres of the written depth (sampled), or None.
        bundle_bytes: Size of the bundle folder.
        gravity_up: The world's up direction written as ``scene.json`` ``up``, or None (the pipeline estimates it).
        gravity_note: Where ``gravity_up`` comes from.
        placeholder_maps: Whether the 2D maps are placeholders.
        maps_to_compute: The kinds of 2D map the bundle lacks (``features``, ``masks``), for the 2D-maps stage.
        has_geometry: Whether ``geometry.ply`` was written.
    """

    bundle: Path
    frames_source: int
    frames_written: int
    dropped: tuple[tuple[str, tuple[str, ...]], ...]
    not_selected: int
    depth_range: tuple[float, float, float] | None
    bundle_bytes: int
    gravity_up: tuple[float, float, float] | None
    gravity_note: str
    placeholder_maps: bool
    has_geometry: bool
    maps_to_compute: tuple[str, ...] = ()

    def summary(self) -> str:
        """A few human-readable lines, for the CLI: kept, dropped and why, depth, size, up, next command."""
        lines = [
            f"wrote {self.frames_written} of {self.frames_source} frames to {self.bundle} "
            f"({self.bundle_bytes / 1e6:.1f} MB); {self.not_selected} left out by stride / key-frame rule / "
            "max frames"
        ]
        lines += [f"dropped {len(ids)} frame(s): {reason}: {id_list(ids)}" for reason, ids in self.dropped]
        if self.depth_range is not None:
            lo, mid, hi = self.depth_range
            lines.append(f"depth {lo:.2f} - {hi:.2f} m (median {mid:.2f} m)")
        up = "unknown" if self.gravity_up is None else "(" + ", ".join(f"{v:g}" for v in self.gravity_up) + ")"
        stored = "scene.json up" if self.gravity_up is not None else "the pipeline will estimate it"
        lines.append(f"gravity up in the world: {up} ({self.gravity_note}; {stored})")
        lines.append(
            "geometry: " + ("geometry.ply from the capture" if self.has_geometry else "none, primitives by TSDF")
        )
        if self.placeholder_maps:
            lines.append("2D maps: placeholders on the first frame (labels are not meaningful)")
        options = " ".join(f"--{_MODEL_OPTION[kind]} FOLDER_OR_HUB_NAME" for kind in self.maps_to_compute)
        if self.maps_to_compute:
            lines.append(
                f"2D maps: no {' nor '.join(self.maps_to_compute)} given; the maps will be computed from the colour "
                f"frames by panogs run {options} (README, 'From your own capture')"
            )
        lines.append(f"next: panogs run {self.bundle} --out {self.bundle}-run" + (f" {options}" if options else ""))
        return "\n".join(lines)


def keyframes_by_motion(poses: list[np.ndarray], min_translation: float, min_rotation: float) -> list[int]:
    """Indices kept by the motion rule: the first, then each that moved or turned enough since the last kept.

    Args:
        poses: Camera-to-world ``(4, 4)`` poses in order.
        min_translation: Metres; 0 leaves translation out of the rule.
        min_rotation: Degrees; 0 leaves rotation out of the rule.

    Example:
        >>> step = [np.eye(4) for _ in range(5)]
        >>> for i, T in enumerate(step): T[0, 3] = 0.04 * i
        >>> keyframes_by_motion(step, 0.05, 0.0)
        [0, 2, 4]
    """
    if not poses:
        return []
    if min_translation <= 0 and min_rotation <= 0:
        return list(range(len(poses)))
    kept = [0]
    for i in range(1, len(poses)):
        last, now = poses[kept[-1]], poses[i]
        moved = float(np.linalg.norm(now[:3, 3] - last[:3, 3]))
        cos = (np.trace(last[:3, :3].T @ now[:3, :3]) - 1.0) / 2.0
        turned = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        # A threshold of 0 is that test switched off, not "any motion": with --min-translation alone, every frame
        # of a hand-held capture turned by some hundredths of a degree and was kept.
        if (min_translation > 0 and moved > min_translation) or (min_rotation > 0 and turned > min_rotation):
            kept.append(i)
    return kept


def quaternion_pose(q_xyzw: np.ndarray, t: np.ndarray) -> np.ndarray:  # (4, 4)
    """A (4, 4) transform from a scalar-last quaternion and a translation; NaN where the quaternion is not unit.

    A quaternion far from unit length (more than 1 %) is a corrupt pose, not one to normalise silently.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    T = np.full((4, 4), np.nan)
    norm = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else np.nan
    if not (abs(norm - 1.0) <= 0.01):
        return T
    x, y, z, w = q / norm
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


def import_capture(
    dst: str | Path,
    capture: Capture,
    selection: FrameSelection,
    maps: MapSources,
    *,
    on_progress: ProgressFn | None = None,
) -> CaptureReport:
    """Write a parsed capture as a bundle at ``dst`` (module docstring: drop, select, stage, rename).

    Raises:
        InputError: if ``dst`` is not empty, no frame survives (the message lists why each was dropped), there
            are no feature maps and no placeholder maps, or a feature map or mask does not read.
    """
    dst = Path(dst)
    require_empty(dst)
    dropped = {reason: list(ids) for reason, ids in capture.dropped.items()}
    valid = _valid_frames(capture.frames, dropped)
    chosen = _select(valid, selection)
    feature_files, mask_files = _map_files(chosen, maps)
    _check_maps(capture.source, feature_files, maps)
    placeholder = maps.placeholder_maps and not any(f is not None for f in feature_files)
    missing = () if placeholder else _missing_maps(feature_files, mask_files)
    chosen_ids = {f.id for f in chosen}
    skipped = [f for f in valid if f.id not in chosen_ids]
    with staged(dst) as stage:
        written, depth_range = _write(
            stage, capture, chosen, skipped, feature_files, mask_files, maps, dropped, on_progress
        )
    return CaptureReport(
        bundle=dst,
        frames_source=len(capture.frames) + sum(len(v) for v in capture.dropped.values()),
        frames_written=written,
        dropped=tuple((reason, tuple(ids)) for reason, ids in dropped.items() if ids),
        not_selected=len(valid) - len(chosen),
        depth_range=depth_range,
        bundle_bytes=sum(p.stat().st_size for p in dst.rglob("*") if p.is_file()),
        gravity_up=capture.gravity_up,
        gravity_note=capture.gravity_note,
        placeholder_maps=placeholder,
        has_geometry=capture.geometry is not None,
        maps_to_compute=missing,
    )


# The ``panogs run`` option that computes each kind of map.
_MODEL_OPTION = {"features": "features-model", "masks": "masks-model"}


def _missing_maps(feature_files: list[Path | None], mask_files: list[Path | None]) -> tuple[str, ...]:
    """The kinds of map no kept frame brings: the 2D-maps stage of ``panogs run`` computes them."""
    kinds = (("masks", mask_files), ("features", feature_files))
    return tuple(kind for kind, files in kinds if not any(f is not None for f in files))


def _valid_frames(frames: list[CaptureFrame], dropped: dict[str, list[str]]) -> list[CaptureFrame]:
    valid = []
    for frame in frames:
        needed = [frame.depth, *([frame.color] if frame.color is not None else []), *frame.extra]
        missing = [p for p in needed if not p.is_file()]
        if missing:
            dropped.setdefault("missing file", []).append(f"{frame.id} ({missing[0]})")
        elif not is_rigid(frame.T_world_cam):
            dropped.setdefault("invalid pose (NaN, infinite or not a rotation)", []).append(frame.id)
        else:
            valid.append(frame)
    return valid


def _select(frames: list[CaptureFrame], selection: FrameSelection) -> list[CaptureFrame]:
    strided = frames[:: selection.stride]
    keep = keyframes_by_motion([f.T_world_cam for f in strided], selection.min_translation, selection.min_rotation)
    moving = [strided[i] for i in keep]
    if selection.max_frames is not None and len(moving) > selection.max_frames:
        spread = np.unique(np.round(np.linspace(0, len(moving) - 1, selection.max_frames)).astype(int))
        moving = [moving[i] for i in spread]
    return moving


def _map_files(frames: list[CaptureFrame], maps: MapSources) -> tuple[list[Path | None], list[Path | None]]:
    def find(folder: Path | None, frame: CaptureFrame, ext: str) -> Path | None:
        if folder is None:
            return None
        for stem in (frame.stem, frame.id):
            if (folder / f"{stem}{ext}").is_file():
                return folder / f"{stem}{ext}"
        return None

    return [find(maps.features, f, ".npy") for f in frames], [find(maps.masks, f, ".png") for f in frames]


def _check_maps(source: str, feature_files: list[Path | None], maps: MapSources) -> None:
    if any(f is not None for f in feature_files):
        return
    if maps.placeholder_maps:
        if maps.vocabulary is not None:
            raise InputError(
                f"import {source}: a vocabulary cannot be used with placeholder maps (their features mean "
                "nothing); leave it out, or pass feature maps of the vocabulary's space"
            )
        return
    if maps.vocabulary is not None and maps.vocabulary.embeddings is not None:
        raise InputError(
            f"import {source}: the vocabulary has embeddings but the bundle has no feature maps whose space they "
            "would be in; leave the embeddings out (the run embeds the names with the features model's text tower)"
        )


def _write(
    stage: Path,
    capture: Capture,
    frames: list[CaptureFrame],
    skipped: list[CaptureFrame],
    feature_files: list[Path | None],
    mask_files: list[Path | None],
    maps: MapSources,
    dropped: dict[str, list[str]],
    on_progress: ProgressFn | None,
) -> tuple[int, tuple[float, float, float] | None]:
    given = any(f is not None for f in feature_files)
    placeholder = maps.placeholder_maps and not given
    dim: int | None = None
    space: str | None = None
    if placeholder:
        dim, space = PLACEHOLDER_DIM, PLACEHOLDER_SPACE
    elif given:
        dim, space = _feature_dim(next(f for f in feature_files if f is not None)), maps.feature_space
    writer = BundleWriter(
        stage,
        name=f"{capture.name} (placeholder maps)" if placeholder else capture.name,
        camera=capture.camera,
        depth_scale=capture.depth_scale,
        feature_dim=dim,
        feature_space=space,
        up=capture.gravity_up,
    )
    vocabulary = placeholder_vocabulary() if placeholder else maps.vocabulary
    if vocabulary is not None:
        writer.write_vocabulary(vocabulary)
    if capture.geometry is not None:
        writer.write_geometry_file(capture.geometry)
    samples: list[np.ndarray] = []
    for done, (frame, feat_path, mask_path) in enumerate(zip(frames, feature_files, mask_files), start=1):
        try:
            depth = capture.read_depth(frame)
        except InputError as exc:
            dropped.setdefault("depth does not decode", []).append(f"{frame.id} ({exc})")
            continue
        feat, mask = _maps_of(feat_path, mask_path, dim or 0)
        if placeholder and dim is not None and writer.num_frames == 0:
            feat = np.full((1, 1, dim), 1.0 / np.sqrt(dim), np.float32)
            mask = np.ones((capture.camera.height, capture.camera.width), np.int64)
        writer.add_frame(frame.id, frame.T_world_cam, depth, color=frame.color, features=feat, masks=mask)
        valid = depth[np.isfinite(depth) & (depth > 0)]
        samples.append(valid[:: max(1, valid.size // _DEPTH_SAMPLE)])
        report(on_progress, done, len(frames))
    if writer.num_frames == 0:
        reasons = "; ".join(f"{reason}: {id_list(tuple(ids))}" for reason, ids in dropped.items() if ids)
        raise InputError(
            f"import {capture.source}: no usable frame among {len(capture.frames)} ({reasons or 'none selected'})"
        )
    for frame in skipped:  # pose only: `panogs render --frame` reaches every frame of the capture
        writer.add_skipped_frame(frame.id, frame.T_world_cam)
    writer.close()
    values = np.concatenate(samples)
    depth_range = None if values.size == 0 else tuple(float(v) for v in np.percentile(values, [0, 50, 100]))
    return writer.num_frames, depth_range  # type: ignore[return-value]


def _feature_dim(path: Path) -> int:
    return feature_dim_of([path], path.parent)


def _maps_of(feat_path: Path | None, mask_path: Path | None, dim: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    feat = mask = None
    if feat_path is not None:
        feat = np.load(feat_path, allow_pickle=False)
        if feat.ndim != 3 or feat.shape[2] != dim or feat.dtype.kind != "f":
            raise InputError(f"import: {feat_path}: feature map {feat.dtype} {feat.shape}, expected (Hf, Wf, {dim})")
        feat = np.ascontiguousarray(feat if feat.dtype in (np.float16, np.float32) else feat.astype(np.float32))
    if mask_path is not None:
        image = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise InputError(f"import: {mask_path}: does not decode as an image")
        mask = masks_to_ids(image)
    return feat, mask
