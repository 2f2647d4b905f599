"""The bundle reader: :class:`Bundle`, a validated bundle whose frames are read one at a time, on demand.

Nothing large is held in memory: depth, colour, feature maps (memory-mapped) and masks are read per frame by the
stages that need them. A ``Bundle`` is made only by validation (:func:`panogs_core.io.bundle.open_bundle`), so every
path it reads has passed the format's rules.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.ply import read_ply_vertices
from panogs_core.types import Camera, Frame, Geometry, GroundTruth, Vocabulary


class ComputedMaps(Protocol):
    """Maps computed for a bundle outside its folder (the 2D-maps stage's checkpoint), read by frame id."""

    def serves(self, kind: str) -> bool:
        """Whether it holds this kind of map (``masks`` or ``features``) in place of the bundle's."""
        ...

    def read_masks(self, frame_id: str) -> np.ndarray: ...

    def read_features(self, frame_id: str) -> np.ndarray: ...


@dataclass(frozen=True)
class Bundle:
    """A validated bundle. Frame data is read on demand by the ``read_*`` methods.

    Attributes:
        root: Bundle folder (extracted when the input was an archive).
        name: ``scene.json`` name.
        camera: Pinhole model of the depth image.
        depth_scale: Depth PNG value per metre.
        feature_dim: ``features.dim`` (D); 0 for a bundle without feature maps (the 2D-maps stage computes them).
        feature_space: ``features.space`` id, e.g. ``clip-vit-b32`` or ``minilm-l6``; ``""`` without feature maps.
        frames: Every frame of the manifest, in manifest order.
        vocabulary: From ``vocabulary.json`` (+ ``.npy``), or None.
        has_geometry: ``geometry.ply`` is present.
        has_ground_truth: ``gt/labels.npz`` is present.
        up: The world's up direction (unit vector) when ``scene.json`` states it, else None.
        skipped_poses: ``(id, camera-to-world pose)`` of the capture's frames the importer left out (pose only,
            ``skipped_frames``), in manifest order.
        computed: Maps computed by the 2D-maps stage that serve the kinds the bundle lacks; a frame's ``masks`` /
            ``features`` path is then relative to them, not to ``root``. None: every map is the bundle's.
    """

    root: Path
    name: str
    camera: Camera
    depth_scale: float
    feature_dim: int
    feature_space: str
    frames: tuple[Frame, ...]
    vocabulary: Vocabulary | None
    has_geometry: bool
    has_ground_truth: bool
    up: tuple[float, float, float] | None = None
    skipped_poses: tuple[tuple[str, np.ndarray], ...] = ()
    computed: ComputedMaps | None = field(default=None, compare=False)

    @property
    def feature_frames(self) -> tuple[Frame, ...]:
        """Frames with a feature map (key frames of the language stages)."""
        return tuple(f for f in self.frames if f.features is not None)

    @property
    def mask_frames(self) -> tuple[Frame, ...]:
        """Frames with an instance mask (key frames of the instance stages)."""
        return tuple(f for f in self.frames if f.masks is not None)

    def read_depth(self, frame: Frame) -> np.ndarray:  # (H, W) float32 metres, 0 = no depth
        """Depth in metres at the camera resolution."""
        raw = read_image_file(self.root, frame.depth)
        return raw.astype(np.float32) / np.float32(self.depth_scale)

    def read_color(self, frame: Frame) -> np.ndarray | None:  # (H, W, 3) uint8 RGB, or None
        """Colour resampled to the camera size, or None when the frame has none."""
        if frame.color is None:
            return None
        rgb = cv2.cvtColor(read_image_file(self.root, frame.color), cv2.COLOR_BGR2RGB)
        size = (self.camera.width, self.camera.height)
        if (rgb.shape[1], rgb.shape[0]) != size:
            # Same field of view at another resolution (docs/scene_format.md §1): resample, do not crop.
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR)
        return rgb

    def read_features(self, frame: Frame) -> np.ndarray:  # (Hf, Wf, D) float16 or float32, as stored
        """The frame's 2D language feature map (memory-mapped where possible).

        Raises:
            InputError: if the frame has no feature map.
        """
        if frame.features is None:
            raise InputError(f"frame {frame.id}: has no feature map")
        if self.computed is not None and self.computed.serves("features"):
            return self.computed.read_features(frame.id)
        return np.load(self.root / frame.features, mmap_mode="r", allow_pickle=False)

    def read_masks(self, frame: Frame) -> np.ndarray:  # (Hm, Wm) int32, 0 = no mask
        """The frame's 2D instance id map.

        Raises:
            InputError: if the frame has no masks.
        """
        if frame.masks is None:
            raise InputError(f"frame {frame.id}: has no masks")
        if self.computed is not None and self.computed.serves("masks"):
            return self.computed.read_masks(frame.id).astype(np.int32)
        return read_image_file(self.root, frame.masks).astype(np.int32)

    def read_geometry(self) -> Geometry | None:
        """Vertices of ``geometry.ply`` in file order, or None."""
        if not self.has_geometry:
            return None
        return geometry_from_vertices(read_ply_vertices(self.root / "geometry.ply"))

    def read_ground_truth(self) -> GroundTruth | None:
        """``gt/labels.npz``, or None."""
        if not self.has_ground_truth:
            return None
        with np.load(self.root / "gt" / "labels.npz", allow_pickle=False) as npz:
            points = npz["points"].astype(np.float32) if "points" in npz.files else None
            return GroundTruth(
                semantic=npz["semantic"].astype(np.int64),
                instance=npz["instance"].astype(np.int64),
                points=points,
            )


def geometry_from_vertices(vertices: dict[str, np.ndarray]) -> Geometry:
    """Build a :class:`Geometry` from PLY vertex properties (x/y/z, optional red/green/blue and nx/ny/nz).

    Integer colours are scaled to ``[0, 1]`` by their type's maximum (uchar 255, ushort 65535).

    Raises:
        InputError: if x, y or z is missing.
    """
    if not {"x", "y", "z"} <= vertices.keys():
        raise InputError(f"geometry: vertices need x, y, z properties, found {sorted(vertices)}")
    points = np.stack([vertices[k] for k in "xyz"], axis=1).astype(np.float32)
    colors = None
    if {"red", "green", "blue"} <= vertices.keys():
        rgb = np.stack([vertices[k] for k in ("red", "green", "blue")], axis=1)
        scale = float(np.iinfo(rgb.dtype).max) if np.issubdtype(rgb.dtype, np.integer) else 1.0
        colors = np.clip(rgb.astype(np.float32) / np.float32(scale), 0.0, 1.0)
    normals = None
    if {"nx", "ny", "nz"} <= vertices.keys():
        normals = np.stack([vertices[k] for k in ("nx", "ny", "nz")], axis=1).astype(np.float32)
    return Geometry(points=points, colors=colors, normals=normals)


def read_image_file(root: Path, rel: str) -> np.ndarray:  # as stored: (H, W) or (H, W, C) BGR
    """Decode ``root / rel`` as stored (no colour conversion); InputError naming ``rel`` when it does not decode."""
    image = cv2.imread(str(root / rel), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{rel}: does not decode as an image")
    return image
