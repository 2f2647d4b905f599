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
import shutil
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.bundle.format import FORMAT_ID, FRAME_FILES, FRAME_ID, MAX_PNG_VALUE
from panogs_core.io.ply import read_ply_vertices, write_ply
from panogs_core.types import Camera, Vocabulary


class BundleWriter:
    """Incrementally write a bundle folder; ``close()`` writes ``scene.json``.

    Args:
        root: Bundle folder (created if missing).
        name: Scene name for ``scene.json``.
        camera: Pinhole model of the depth images.
        depth_scale: Depth PNG value per metre (1000 = millimetres).
        feature_dim: ``features.dim`` (D) of every feature map; None (with ``feature_space`` None): a bundle
            without feature maps, whose ``scene.json`` has no ``features`` (the 2D-maps stage computes them).
        feature_space: ``features.space`` id, e.g. ``clip-vit-b32``.
        color_format: ``"jpg"`` or ``"png"`` for colour written from arrays.
        jpeg_quality: JPEG quality 0-100 when ``color_format == "jpg"``.
        up: The world's up direction when the source knows it (``scene.json`` ``up``, stored as given).

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
        feature_dim: int | None,
        feature_space: str | None,
        color_format: Literal["jpg", "png"] = "jpg",
        jpeg_quality: int = 95,
        up: tuple[float, float, float] | None = None,
    ) -> None:
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise InputError(f"BundleWriter: depth_scale must be > 0, got {depth_scale}")
        if (feature_dim is None) != (feature_space is None):
            raise InputError("BundleWriter: feature_dim and feature_space are given together or not at all")
        if feature_dim is not None and int(feature_dim) <= 0:
            raise InputError(f"BundleWriter: feature_dim must be > 0, got {feature_dim}")
        if color_format not in ("jpg", "png"):
            raise InputError(f"BundleWriter: color_format must be 'jpg' or 'png', got {color_format!r}")
        if up is not None and not (len(up) == 3 and np.all(np.isfinite(up)) and np.linalg.norm(up) > 1e-9):
            raise InputError(f"BundleWriter: up must be 3 finite numbers, not all 0, got {up}")
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.name = name
        self.camera = camera
        self.depth_scale = float(depth_scale)
        self.feature_dim = None if feature_dim is None else int(feature_dim)
        self.feature_space = feature_space
        self.color_format = color_format
        self.jpeg_quality = int(jpeg_quality)
        self.up = None if up is None else [float(v) for v in up]
        self._frames: list[dict[str, Any]] = []
        self._skipped: list[dict[str, Any]] = []
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
            entry["color"] = self._copy(color, f"color/{frame_id}{ext}", FRAME_FILES["color"], link=False)
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
            entry["color"] = self._copy(color, f"color/{frame_id}{ext}", FRAME_FILES["color"], link)
        if features is not None:
            entry["features"] = self._copy(features, f"features/{frame_id}.npy", (".npy",), link)
        if masks is not None:
            entry["masks"] = self._copy(masks, f"masks/{frame_id}.png", (".png",), link)
        self._commit(frame_id, entry)

    def add_skipped_frame(self, frame_id: str, T_world_cam: np.ndarray) -> None:
        """Record a capture frame left out of the bundle, by its pose only (``skipped_frames``), so that a run can
        still be rendered from it.

        Raises:
            InputError: if the id is reused or unsafe, or the pose is not a finite (4, 4).
        """
        entry = self._new_entry(frame_id, T_world_cam)
        self._ids.add(frame_id)
        self._skipped.append(entry)

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
        manifest: dict[str, Any] = {
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
        if self.up is not None:
            manifest["up"] = self.up
        if self._skipped:
            manifest["skipped_frames"] = self._skipped
        if self.feature_dim is None:
            del manifest["features"]
        (self.root / "scene.json").write_text(json.dumps(manifest, indent=1), encoding="utf-8")
        return self.root

    # -- internals -------------------------------------------------------------------------------------------

    def _new_entry(self, frame_id: str, T_world_cam: np.ndarray) -> dict[str, Any]:
        if not isinstance(frame_id, str) or not FRAME_ID.match(frame_id):
            raise InputError(f"BundleWriter: frame id {frame_id!r} must match {FRAME_ID.pattern}")
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
        return np.clip(raw, 0, MAX_PNG_VALUE).astype(np.uint16)

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
    if ids.size and (ids.min() < 0 or ids.max() > MAX_PNG_VALUE):
        raise InputError(f"add_frame: mask ids must lie in [0, {MAX_PNG_VALUE}]")
    return ids.astype(np.uint16)


def _check_n3(arr: np.ndarray, what: str, n: int | None) -> np.ndarray:  # (N, 3)
    a = np.asarray(arr)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and len(a) != n):
        expected = f"({n}, 3)" if n is not None else "(N, 3)"
        raise InputError(f"{what}: shape {a.shape}, expected {expected}")
    return a
