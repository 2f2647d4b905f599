"""Small frozen dataclasses shared by the loader, the stages and the run reader: camera, frames, vocabulary, ground
truth, and the instance table's rows.

Conventions (see docs/conventions.md): world frame in metres; poses are camera-to-world ``T_world_cam`` (4, 4)
with OpenCV camera axes (x right, y down, z forward); labels are int64 and -1 means void everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

ClassKind = Literal["thing", "stuff"]


@dataclass(frozen=True)
class Camera:
    """Pinhole model of the depth image; shared by every frame of a scene."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:  # (3, 3) float64
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera at another resolution: same field of view, pixel centres (at integers) kept.

        Example:
            >>> Camera(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5).scaled(320, 240).cx
            159.5
        """
        sx, sy = width / self.width, height / self.height
        return Camera(
            width=width,
            height=height,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )


@dataclass(frozen=True)
class Frame:
    """One frame of the manifest. Paths are relative to the bundle root; ``None`` means absent."""

    id: str
    T_world_cam: np.ndarray  # (4, 4) float64, camera-to-world
    depth: str
    color: str | None = None
    features: str | None = None
    masks: str | None = None


@dataclass(frozen=True)
class Vocabulary:
    """The label set: class names, thing/stuff kinds, and optionally their text embeddings."""

    names: tuple[str, ...]
    kinds: tuple[ClassKind, ...]
    embeddings: np.ndarray | None = None  # (L, D) float32, rows L2-normalised

    def __post_init__(self) -> None:
        if len(self.names) != len(self.kinds):
            raise ValueError(f"vocabulary: {len(self.names)} names but {len(self.kinds)} kinds")
        if self.embeddings is not None and self.embeddings.shape[0] != len(self.names):
            raise ValueError(f"vocabulary: {len(self.names)} names but embeddings of shape {self.embeddings.shape}")

    @property
    def is_thing(self) -> np.ndarray:  # (L,) bool
        """Per class: True for things (countable objects), False for stuff."""
        return np.array([k == "thing" for k in self.kinds], dtype=bool)


@dataclass(frozen=True)
class GroundTruth:
    """Per-point ground truth of ``gt/labels.npz``."""

    semantic: np.ndarray  # (G,) int64, index into the vocabulary, -1 = unannotated
    instance: np.ndarray  # (G,) int64, unique within the scene, -1 = none
    points: np.ndarray | None = None  # (G, 3) float32; None = per vertex of geometry.ply, in order


@dataclass(frozen=True)
class Geometry:
    """Vertices of ``geometry.ply`` (mesh or point cloud), in file order."""

    points: np.ndarray  # (N, 3) float32, world frame, metres
    colors: np.ndarray | None = None  # (N, 3) float32 in [0, 1]
    normals: np.ndarray | None = None  # (N, 3) float32 (from the file, if it had them)


@dataclass(frozen=True)
class InstanceInfo:
    """One panoptic segment: a thing instance, or all primitives of one stuff class.

    ``score`` is the mean, over the instance's primitives, of the softmax probability (over the vocabulary, at
    ``LabelingConfig.score_temperature``) of the instance's class; in ``[0, 1]``.
    """

    id: int
    class_index: int
    class_name: str
    kind: str  # "thing" | "stuff"
    score: float
    num_points: int
    centroid: np.ndarray  # (3,) float32, mean position
    bbox_min: np.ndarray  # (3,) float32, axis-aligned box
    bbox_max: np.ndarray  # (3,) float32
    feature: np.ndarray  # (D,) float32, unit mean feature

    def to_json(self, *, with_feature: bool = False) -> dict[str, Any]:
        """Plain dict (ints, floats, lists); the ``(D,)`` feature only when asked."""
        out: dict[str, Any] = {
            "id": int(self.id),
            "class_index": int(self.class_index),
            "class_name": self.class_name,
            "kind": self.kind,
            "score": float(self.score),
            "num_points": int(self.num_points),
            "centroid": [float(v) for v in self.centroid],
            "bbox_min": [float(v) for v in self.bbox_min],
            "bbox_max": [float(v) for v in self.bbox_max],
        }
        if with_feature:
            out["feature"] = [float(v) for v in self.feature]
        return out
