"""The rules of the bundle format ``panogs-scene/1`` (docs/scene_format.md) that its reader, its validation and its
writer share: the format id, the manifest's keys, the files a frame may name, and the limits on what they declare.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from panogs_core.bounded_json import JsonLimits

FORMAT_ID = "panogs-scene/1"

# Frame ids become file names: keep them to a portable alphabet, never a path.
FRAME_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")
FRAME_FILES: dict[str, tuple[str, ...]] = {  # frame key -> allowed extensions
    "depth": (".png",),
    "color": (".png", ".jpg", ".jpeg"),
    "features": (".npy",),
    "masks": (".png",),
}
FRAME_KEYS = frozenset({"id", "pose", *FRAME_FILES})
TOP_KEYS = frozenset({"format", "name", "camera", "depth_scale", "features", "frames"})
FEATURE_DTYPES = (np.dtype(np.float16), np.dtype(np.float32))
GT_KEYS = ("semantic", "instance", "points")  # the members of gt/labels.npz that are read (docs/scene_format.md §4)
ROTATION_TOL = 1e-3  # docs/scene_format.md §2.1: orthonormal rotation, det 1, tolerance 1e-3
LAST_ROW_TOL = 1e-6  # the last pose row is exact in any sane writer; allow float printing noise only
MAX_PNG_VALUE = 65535  # depth and mask PNGs are at most 16-bit
DEFAULT_MAX_IMAGE_PIXELS = 100_000_000  # 10000 x 10000; the 8K UHD frame (7680 x 4320) is 33 million
# gt/labels.npz is read whole during validation: 1 GiB holds 38 million labelled points with positions (28 bytes
# each), 10x a large ScanNet or Replica mesh.
DEFAULT_MAX_GROUND_TRUTH_BYTES = 1024**3


@dataclass(frozen=True)
class BundleLimits:
    """Limits on what one bundle's files may declare, checked before anything large is read or decoded.

    Attributes:
        json: Depth, size and integer limits of ``scene.json`` and ``vocabulary.json``.
        max_image_pixels: Most pixels (width x height) of one image, and cells (Hf x Wf) of one feature map.
        max_ground_truth_bytes: Most bytes the arrays of ``gt/labels.npz`` may expand to (their declared sizes
            are checked before any is decompressed).
    """

    json: JsonLimits = field(default_factory=JsonLimits)
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    max_ground_truth_bytes: int = DEFAULT_MAX_GROUND_TRUTH_BYTES
