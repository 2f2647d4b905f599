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
# What validation requires of any frame id (the writer's alphabet above is stricter): printable text of at most
# this many characters, since ids reach logs, file names of computed maps and the viewer's lists.
MAX_FRAME_ID_CHARS = 128
FRAME_FILES: dict[str, tuple[str, ...]] = {  # frame key -> allowed extensions
    "depth": (".png",),
    "color": (".png", ".jpg", ".jpeg"),
    "features": (".npy",),
    "masks": (".png",),
}
FRAME_KEYS = frozenset({"id", "pose", *FRAME_FILES})
# "up" and "skipped_frames" are optional (docs/scene_format.md §2.5, §2.6): a reader that predates them warns and
# ignores them, which is why they did not need a new format id.
TOP_KEYS = frozenset({"format", "name", "camera", "depth_scale", "features", "frames", "up", "skipped_frames"})
SKIPPED_FRAME_KEYS = frozenset({"id", "pose"})
FEATURE_DTYPES = (np.dtype(np.float16), np.dtype(np.float32))
GT_KEYS = ("semantic", "instance", "points")  # the members of gt/labels.npz that are read (docs/scene_format.md §4)
ROTATION_TOL = 1e-3  # docs/scene_format.md §2.1: orthonormal rotation, det 1, tolerance 1e-3
LAST_ROW_TOL = 1e-6  # the last pose row is exact in any sane writer; allow float printing noise only
MAX_PNG_VALUE = 65535  # depth and mask PNGs are at most 16-bit
DEFAULT_MAX_IMAGE_PIXELS = 100_000_000  # 10000 x 10000; the 8K UHD frame (7680 x 4320) is 33 million
# gt/labels.npz is read whole during validation: 1 GiB holds 38 million labelled points with positions (28 bytes
# each), 10x a large ScanNet or Replica mesh.
DEFAULT_MAX_GROUND_TRUTH_BYTES = 1024**3
# features.dim: CLIP and LSeg are 512-d, CLIP ViT-L/14 and OpenSeg 768, SigLIP so400m 1152, CLIP bigG 1280. The
# vocabulary's embeddings (classes x dim) and every feature map's last axis are bounded by it.
DEFAULT_MAX_FEATURE_DIM = 2048
# vocabulary.json: ScanNet200 has 200 classes, LVIS 1,203, ADE20K-full 3,688. With the dim bound, vocabulary.npy
# holds at most 64 MiB (float64) and its float32 copy 32 MiB.
DEFAULT_MAX_CLASSES = 4096
# The chunks of one PNG that validation walks: libpng writes 8 KiB IDAT chunks and a row-per-chunk writer about one
# chunk per 200 bytes; a million empty chunks (12 MB, 23 KB zipped) is neither, and cost 21 s of CPU per frame.
PNG_CHUNKS_PER_KIB = 8
PNG_CHUNKS_FREE = 64


@dataclass(frozen=True)
class BundleLimits:
    """Limits on what one bundle's files may declare, checked before anything large is read or decoded.

    Attributes:
        json: Depth, size and integer limits of ``scene.json`` and ``vocabulary.json``.
        max_image_pixels: Most pixels (width x height) of one image, and cells (Hf x Wf) of one feature map.
        max_ground_truth_bytes: Most bytes the arrays of ``gt/labels.npz`` may expand to (their declared sizes
            are checked before any is decompressed).
        max_feature_dim: Largest ``features.dim``.
        max_classes: Most classes in ``vocabulary.json``.
        max_cpu_s: CPU seconds (of the validating thread, from the start of :func:`open_bundle`: the extraction
            counts) after which validation stops at the next file and refuses the bundle; None: no budget. The
            checks are bounded one by one; this bounds their sum, whatever the bundle holds.
    """

    json: JsonLimits = field(default_factory=JsonLimits)
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    max_ground_truth_bytes: int = DEFAULT_MAX_GROUND_TRUTH_BYTES
    max_feature_dim: int = DEFAULT_MAX_FEATURE_DIM
    max_classes: int = DEFAULT_MAX_CLASSES
    max_cpu_s: float | None = None


def max_png_chunks(file_bytes: int) -> int:
    """Most chunks a PNG of ``file_bytes`` may hold before validation refuses it (see ``PNG_CHUNKS_PER_KIB``)."""
    return PNG_CHUNKS_FREE + PNG_CHUNKS_PER_KIB * (file_bytes // 1024)
