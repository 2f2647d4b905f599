"""Write scene bundles (``panogs-scene/1``, docs/scene_format.md) from arrays or from existing files.

Used by the synthetic generator, the dataset importers and the tests. The writer checks what it is given
against the format as it goes (sizes, dtypes, feature dimension, pose shape) so that a bundle it writes opens
cleanly; ``open_bundle`` remains the judge of any bundle.

Example:
    >>> import tempfile
    >>> from panogs_core.types import Camera
    >>> cam = Camera(width=8, height=6, fx=5.0, fy=5.0, cx=3.5, cy=2.5)
    >>> w = BundleWriter(tempfile.mkdtemp(), name="tiny", camera=cam, feature_dim=4, feature_space="test")
    >>> w.add_frame("0", np.eye(4), np.ones((6, 8)), features=np.ones((3, 4, 4), np.float32),
    ...             masks=np.ones((6, 8), np.int32))
    >>> (w.close() / "scene.json").is_file()
    True
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.ground_truth import load_ground_truth, vocabulary_for_ground_truth
from panogs_core.io.ply import read_ply_vertices, write_ply
from panogs_core.progress import ProgressFn, report
from panogs_core.types import Camera, Vocabulary

FORMAT_ID = "panogs-scene/1"

# Frame ids become file names: keep them to a portable alphabet, never a path.
_FRAME_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")
_UINT16_MAX = 65535
_COLOR_EXTS = (".jpg", ".jpeg", ".png")


class BundleWriter:
    """Incrementally write a bundle folder; ``close()`` writes ``scene.json``.

    Args:
        root: Bundle folder (created if missing).
        name: Scene name for ``scene.json``.
        camera: Pinhole model of the depth images.
        depth_scale: Depth PNG value per metre (1000 = millimetres).
        feature_dim: ``features.dim`` (D) of every feature map.
        feature_space: ``features.space`` id, e.g. ``clip-vit-b32``.
        color_format: ``"jpg"`` or ``"png"`` for colour written from arrays.
        jpeg_quality: JPEG quality 0-100 when ``color_format == "jpg"``.

    Raises:
        InputError: for a non-positive depth scale or feature dim, or an unknown colour format.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        name: str,
        camera: Camera,
        depth_scale: float = 1000.0,
        feature_dim: int,
        feature_space: str,
        color_format: Literal["jpg", "png"] = "jpg",
        jpeg_quality: int = 95,
    ) -> None:
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise InputError(f"BundleWriter: depth_scale must be > 0, got {depth_scale}")
        if int(feature_dim) <= 0:
            raise InputError(f"BundleWriter: feature_dim must be > 0, got {feature_dim}")
        if color_format not in ("jpg", "png"):
            raise InputError(f"BundleWriter: color_format must be 'jpg' or 'png', got {color_format!r}")
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.name = name
        self.camera = camera
        self.depth_scale = float(depth_scale)
        self.feature_dim = int(feature_dim)
        self.feature_space = feature_space
        self.color_format = color_format
        self.jpeg_quality = int(jpeg_quality)
        self._frames: list[dict[str, Any]] = []
        self._ids: set[str] = set()
        self._vocabulary_size: int | None = None

    def __enter__(self) -> BundleWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()

    @property
    def num_frames(self) -> int:
        """Frames added so far."""
        return len(self._frames)

    def add_frame(
        self,
        frame_id: str,
        T_world_cam: np.ndarray,  # (4, 4) camera-to-world, OpenCV axes, metres
        depth_m: np.ndarray,  # (H, W) float metres; <= 0 or non-finite = no depth
        *,
        color: np.ndarray | str | Path | None = None,  # (Hc, Wc, 3) uint8 RGB, any size; or a file
        features: np.ndarray | None = None,  # (Hf, Wf, D) float16 / float32
        masks: np.ndarray | None = None,  # (Hm, Wm) int, 0 = no mask, values <= 65535
    ) -> None:
        """Write one frame from arrays.

        Args:
            frame_id: Unique id, used as the file stem.
            T_world_cam: Camera-to-world pose ``(4, 4)``.
            depth_m: Depth in metres ``(H, W)`` at the camera size; stored as
                ``round(depth_m * depth_scale)`` clipped to uint16, 0 where invalid.
            color: RGB ``(Hc, Wc, 3)`` uint8, or an existing ``.jpg``/``.png`` file to copy as it is.
            features: Feature map ``(Hf, Wf, D)`` float16/float32 with ``D == feature_dim``.
            masks: Instance id map ``(Hm, Wm)`` integers in ``[0, 65535]``, stored as a 16-bit PNG.

        Raises:
            InputError: if the id is reused or unsafe, or an array has the wrong shape, dtype or range.
        """
        entry = self._new_entry(frame_id, T_world_cam)
        entry["depth"] = self._write_png(f"depth/{frame_id}.png", self._encode_depth(depth_m))
        if isinstance(color, str | Path):
            ext = Path(color).suffix.lower()
            entry["color"] = self._copy(color, f"color/{frame_id}{ext}", _COLOR_EXTS, link=False)
        elif color is not None:
            entry["color"] = self._write_color(frame_id, color)
        if features is not None:
            entry["features"] = self._write_features(frame_id, features)
        if masks is not None:
            entry["masks"] = self._write_png(f"masks/{frame_id}.png", _encode_masks(masks))
        self._commit(frame_id, entry)

    def add_frame_files(
        self,
        frame_id: str,
        T_world_cam: np.ndarray,  # (4, 4)
        *,
        depth: str | Path,
        color: str | Path | None = None,
        features: str | Path | None = None,
        masks: str | Path | None = None,
        link: bool = False,
    ) -> None:
        """Add one frame by copying existing files (for importers); contents are not converted.

        Args:
            frame_id: Unique id, used as the file stem.
            T_world_cam: Camera-to-world pose ``(4, 4)``.
            depth: 16-bit PNG at the camera size, values per ``depth_scale``.
            color: ``.jpg``/``.jpeg``/``.png`` colour image (extension kept).
            features: ``.npy`` feature map.
            masks: ``.png`` id map.
            link: Hard-link instead of copying where the file system allows (falls back to a copy).

        Raises:
            InputError: if the id is reused or unsafe, or a source file is missing or has an unexpected
                extension.
        """
        entry = self._new_entry(frame_id, T_world_cam)
        entry["depth"] = self._copy(depth, f"depth/{frame_id}.png", (".png",), link)
        if color is not None:
            ext = Path(color).suffix.lower()
            entry["color"] = self._copy(color, f"color/{frame_id}{ext}", _COLOR_EXTS, link)
        if features is not None:
            entry["features"] = self._copy(features, f"features/{frame_id}.npy", (".npy",), link)
        if masks is not None:
            entry["masks"] = self._copy(masks, f"masks/{frame_id}.png", (".png",), link)
        self._commit(frame_id, entry)

    def write_geometry(
        self,
        points: np.ndarray,  # (N, 3) float, world, metres
        colors: np.ndarray | None = None,  # (N, 3) uint8, or float in [0, 1]
        normals: np.ndarray | None = None,  # (N, 3) float
        faces: np.ndarray | None = None,  # (F, 3) int
    ) -> Path:
        """Write ``geometry.ply`` (float32 x/y/z, optional uchar red/green/blue and float nx/ny/nz).

        Raises:
            InputError: if an array is not ``(N, 3)`` with the same N as ``points``.
        """
        pts = _check_n3(points, "points", None)
        fields: dict[str, np.ndarray] = {k: pts[:, i].astype(np.float32) for i, k in enumerate("xyz")}
        if normals is not None:
            nrm = _check_n3(normals, "normals", len(pts)).astype(np.float32)
            fields.update({k: nrm[:, i] for i, k in enumerate(("nx", "ny", "nz"))})
        if colors is not None:
            col = _check_n3(colors, "colors", len(pts))
            if col.dtype != np.uint8:
                col = np.round(np.clip(col.astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)
            fields.update({k: col[:, i] for i, k in enumerate(("red", "green", "blue"))})
        return write_ply(self.root / "geometry.ply", fields, faces=faces)

    def write_geometry_file(self, src: str | Path) -> Path:
        """Copy an existing PLY (mesh or point cloud) as ``geometry.ply``; its vertex order is kept.

        Raises:
            InputError: if ``src`` does not parse as PLY.
        """
        read_ply_vertices(src)  # refuse a file the bundle validator would refuse, before copying it
        dst = self.root / "geometry.ply"
        shutil.copyfile(src, dst)
        return dst

    def write_vocabulary(self, vocabulary: Vocabulary) -> Path:
        """Write ``vocabulary.json`` (+ ``vocabulary.npy`` float32 when embeddings are present).

        Raises:
            InputError: if the embeddings are not ``(L, feature_dim)``.
        """
        doc: dict[str, Any] = {"classes": [{"name": n, "kind": k} for n, k in zip(vocabulary.names, vocabulary.kinds)]}
        if vocabulary.embeddings is not None:
            emb = np.asarray(vocabulary.embeddings, dtype=np.float32)
            if emb.shape != (len(vocabulary.names), self.feature_dim):
                raise InputError(
                    f"write_vocabulary: embeddings {emb.shape}, expected ({len(vocabulary.names)}, {self.feature_dim})"
                )
            np.save(self.root / "vocabulary.npy", np.ascontiguousarray(emb), allow_pickle=False)
            doc["embeddings"] = "vocabulary.npy"
        path = self.root / "vocabulary.json"
        path.write_text(json.dumps(doc, indent=1), encoding="utf-8")
        self._vocabulary_size = len(vocabulary.names)
        return path

    def write_ground_truth(
        self,
        semantic: np.ndarray,  # (G,) int, class index, -1 = unannotated
        instance: np.ndarray,  # (G,) int, -1 = none
        points: np.ndarray | None = None,  # (G, 3) float; None = per vertex of geometry.ply
    ) -> Path:
        """Write ``gt/labels.npz`` (int64 semantic/instance, optional float32 points).

        Raises:
            InputError: if the arrays are not integer ``(G,)`` of one length (and ``(G, 3)`` points).
        """
        sem, ins = np.asarray(semantic), np.asarray(instance)
        for arr, what in ((sem, "semantic"), (ins, "instance")):
            if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
                raise InputError(f"write_ground_truth: {what} must be (G,) integers, got {arr.dtype} {arr.shape}")
        if len(sem) != len(ins):
            raise InputError(f"write_ground_truth: semantic has {len(sem)} values, instance {len(ins)}")
        arrays = {"semantic": sem.astype(np.int64), "instance": ins.astype(np.int64)}
        if points is not None:
            arrays["points"] = _check_n3(points, "points", len(sem)).astype(np.float32)
        path = self.root / "gt" / "labels.npz"
        path.parent.mkdir(exist_ok=True)
        np.savez(path, allow_pickle=False, **arrays)
        return path

    def close(self) -> Path:
        """Write ``scene.json`` and return the bundle root.

        Raises:
            InputError: if no frame was added.
        """
        if not self._frames:
            raise InputError("BundleWriter: a bundle needs at least one frame")
        cam = self.camera
        manifest = {
            "format": FORMAT_ID,
            "name": self.name,
            "camera": {
                "width": int(cam.width),
                "height": int(cam.height),
                "fx": float(cam.fx),
                "fy": float(cam.fy),
                "cx": float(cam.cx),
                "cy": float(cam.cy),
            },
            "depth_scale": self.depth_scale,
            "features": {"dim": self.feature_dim, "space": self.feature_space},
            "frames": self._frames,
        }
        (self.root / "scene.json").write_text(json.dumps(manifest, indent=1), encoding="utf-8")
        return self.root

    # -- internals -------------------------------------------------------------------------------------------

    def _new_entry(self, frame_id: str, T_world_cam: np.ndarray) -> dict[str, Any]:
        if not isinstance(frame_id, str) or not _FRAME_ID.match(frame_id):
            raise InputError(f"BundleWriter: frame id {frame_id!r} must match {_FRAME_ID.pattern}")
        if frame_id in self._ids:
            raise InputError(f"BundleWriter: frame id {frame_id!r} used twice")
        pose = np.asarray(T_world_cam, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise InputError(f"BundleWriter: frame {frame_id}: pose must be a finite (4, 4), got {pose.shape}")
        return {"id": frame_id, "pose": pose.tolist()}

    def _commit(self, frame_id: str, entry: dict[str, Any]) -> None:
        self._ids.add(frame_id)
        self._frames.append(entry)

    def _encode_depth(self, depth_m: np.ndarray) -> np.ndarray:  # (H, W) uint16
        depth = np.asarray(depth_m, dtype=np.float64)
        expected = (self.camera.height, self.camera.width)
        if depth.shape != expected:
            raise InputError(f"add_frame: depth shape {depth.shape}, expected {expected} (camera height, width)")
        valid = np.isfinite(depth) & (depth > 0)
        raw = np.where(valid, np.round(np.where(valid, depth, 0.0) * self.depth_scale), 0.0)
        return np.clip(raw, 0, _UINT16_MAX).astype(np.uint16)

    def _write_color(self, frame_id: str, color: np.ndarray) -> str:
        rgb = np.asarray(color)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise InputError(f"add_frame: color must be (H, W, 3) uint8 RGB, got {rgb.dtype} {rgb.shape}")
        rel = f"color/{frame_id}.{self.color_format}"
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.color_format == "jpg" else []
        bgr = np.ascontiguousarray(rgb[:, :, ::-1])  # OpenCV writes BGR
        return self._imwrite(rel, bgr, params)

    def _write_features(self, frame_id: str, features: np.ndarray) -> str:
        feat = np.asarray(features)
        if feat.ndim != 3 or feat.dtype not in (np.float16, np.float32):
            raise InputError(f"add_frame: features must be (Hf, Wf, D) float16/32, got {feat.dtype} {feat.shape}")
        if feat.shape[2] != self.feature_dim:
            raise InputError(f"add_frame: features last dim {feat.shape[2]}, expected {self.feature_dim}")
        rel = f"features/{frame_id}.npy"
        (self.root / "features").mkdir(exist_ok=True)
        np.save(self.root / rel, np.ascontiguousarray(feat), allow_pickle=False)
        return rel

    def _write_png(self, rel: str, image: np.ndarray) -> str:
        return self._imwrite(rel, image, [cv2.IMWRITE_PNG_COMPRESSION, 1])  # speed over size

    def _imwrite(self, rel: str, image: np.ndarray, params: list[int]) -> str:
        path = self.root / rel
        path.parent.mkdir(exist_ok=True)
        if not cv2.imwrite(str(path), image, params):
            raise InputError(f"BundleWriter: could not write {rel}")
        return rel

    def _copy(self, src: str | Path, rel: str, exts: tuple[str, ...], link: bool) -> str:
        source = Path(src)
        if source.suffix.lower() not in exts:
            raise InputError(f"add_frame_files: {source.name}: expected one of {', '.join(exts)}")
        if not source.is_file():
            raise InputError(f"add_frame_files: {source} does not exist")
        dst = self.root / rel
        dst.parent.mkdir(exist_ok=True)
        if dst.exists():
            dst.unlink()
        if link:
            try:
                os.link(source, dst)  # hard link: a symlink would be refused by the validator
                return rel
            except OSError:
                pass  # other file system, or links not allowed: copy instead
        shutil.copyfile(source, dst)
        return rel


def _encode_masks(masks: np.ndarray) -> np.ndarray:  # (Hm, Wm) uint16
    ids = np.asarray(masks)
    if ids.ndim != 2 or not np.issubdtype(ids.dtype, np.integer):
        raise InputError(f"add_frame: masks must be (Hm, Wm) integers, got {ids.dtype} {ids.shape}")
    if ids.size and (ids.min() < 0 or ids.max() > _UINT16_MAX):
        raise InputError(f"add_frame: mask ids must lie in [0, {_UINT16_MAX}]")
    return ids.astype(np.uint16)


def _check_n3(arr: np.ndarray, what: str, n: int | None) -> np.ndarray:  # (N, 3)
    a = np.asarray(arr)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and len(a) != n):
        expected = f"({n}, 3)" if n is not None else "(N, 3)"
        raise InputError(f"{what}: shape {a.shape}, expected {expected}")
    return a


# -- importer support: shared by the ScanNet and Replica importers -------------------------------------------


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
                + _id_list(self.frames_skipped_invalid_pose)
            )
        if self.frames_skipped_missing:
            lines.append(
                f"skipped {len(self.frames_skipped_missing)} frames without pose or depth: "
                + _id_list(self.frames_skipped_missing)
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
    depth_ok = png_info(depth) == (writer.camera.width, writer.camera.height, 16, 0)
    masks_ok = frame.masks is None or png_info(frame.masks)[2:] in ((8, 0), (16, 0))
    features_ok = frame.features is None or _npy_is_bundle_ready(frame.features, writer.feature_dim)
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
        features=None if frame.features is None else _load_features(frame.features, writer.feature_dim),
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
    if ids.max(initial=0) > _UINT16_MAX:
        raise InputError(f"import: {len(colours)} mask colours, at most {_UINT16_MAX} fit a 16-bit PNG")
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


def _id_list(ids: tuple[str, ...], limit: int = 10) -> str:
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
    writer = BundleWriter(
        dst, name=name, camera=camera, depth_scale=depth_scale, feature_dim=feature_dim, feature_space=feature_space
    )
    if geometry is not None:
        writer.write_geometry_file(geometry)
    if vocabulary is not None:
        writer.write_vocabulary(vocabulary)
    if gt is not None:
        writer.write_ground_truth(gt.semantic, gt.instance, gt.points)
    return write_source_frames(writer, frames, on_progress=on_progress)
