"""Import a 7-Scenes sequence (the same layout serves 3DMatch / SUN3D exports and tsdf-fusion-python's ``data/``).

Source layout::

    <src>/frame-<i>.color.jpg | .color.png   RGB, 640x480 on a Kinect v1
    <src>/frame-<i>.depth.png                uint16 millimetres; 0 and 65535 mean no measurement
    <src>/frame-<i>.pose.txt                 4x4 camera-to-world, OpenCV axes
    <src>/camera-intrinsics.txt              3x3 pinhole matrix (7-Scenes: fx = fy = 585, cx 320, cy 240)
    <features>/<i>.npy, <masks>/<i>.png      optional, as the ScanNet importer's (``<i>`` or ``<i:06d>``)

The capture has no 2D feature maps nor masks, which a bundle needs on at least one frame (docs/scene_format.md).
``placeholder_maps`` writes, on the first frame only, a constant 1 x 1 feature map and a one-segment mask, in a
feature space of its own (``placeholder``) with a two-class label set embedded in it (``surface`` and ``object``),
and names the bundle ``<name> (placeholder maps)``: enough to open the bundle, fit its Gaussians (the photometric
benchmark, docs/gaussians.md) and run ``panogs run`` end to end (everything is ``surface``), never meaningful
labels. Colour and depth of a Kinect v1 are registered only
roughly; the importer keeps both as they are (docs/gaussians.md says what that costs the fit).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.io.importers.common import ImportReport, is_rigid, read_matrix, require_empty, staged
from panogs_core.progress import ProgressFn, report
from panogs_core.types import Camera, Vocabulary

logger = logging.getLogger(__name__)

SEVENSCENES_DEPTH_SCALE = 1000.0  # millimetres
_NO_DEPTH = 65535  # 7-Scenes marks a pixel without a measurement with 65535 as well as 0
_FRAME = re.compile(r"frame-(\d+)\.depth\.png$")
PLACEHOLDER_DIM = 8  # the placeholder feature map's dimension
PLACEHOLDER_SPACE = "placeholder"  # its feature space: no text encoder, so the bundle carries its label set


def placeholder_vocabulary() -> Vocabulary:
    """The label set of a placeholder bundle: ``surface`` (stuff) is the constant feature, ``object`` (thing) an
    axis, so every primitive is ``surface``."""
    surface = np.full(PLACEHOLDER_DIM, 1.0 / np.sqrt(PLACEHOLDER_DIM), np.float32)
    axis = np.zeros(PLACEHOLDER_DIM, np.float32)
    axis[0] = 1.0
    return Vocabulary(("surface", "object"), ("stuff", "thing"), np.stack([surface, axis]))


def import_sevenscenes(
    src: str | Path,
    dst: str | Path,
    *,
    stride: int = 1,
    features: str | Path | None = None,
    masks: str | Path | None = None,
    placeholder_maps: bool = False,
    vocabulary: Vocabulary | None = None,
    name: str | None = None,
    feature_space: str = "clip-vit-b32",
    on_progress: ProgressFn | None = None,
) -> ImportReport:
    """Convert a 7-Scenes sequence folder into a bundle at ``dst`` (module docstring).

    Args:
        src: The sequence folder (``frame-*.{color.jpg,depth.png,pose.txt}``, ``camera-intrinsics.txt``).
        dst: Bundle folder to create (must not exist or be empty).
        stride: Keep every ``stride``-th frame of the sorted list.
        features: Folder of per-frame feature maps ``<i>.npy``, or None.
        masks: Folder of per-frame instance masks ``<i>.png``, or None.
        placeholder_maps: Without ``features``: write the placeholder maps on the first frame (module docstring).
        vocabulary: Label set to write, or None.
        name: Scene name; the source folder name by default.
        feature_space: ``features.space`` id of the feature maps.
        on_progress: Called with ``(done, total)`` per frame.

    Raises:
        InputError: for a missing intrinsics file, no frames, unreadable files, or ``dst`` not empty. Without
            feature maps nor ``placeholder_maps`` the bundle has no maps: ``panogs run --masks-model ...
            --features-model ...`` computes them.
    """
    src, dst = Path(src), Path(dst)
    if stride < 1:
        raise InputError(f"import_sevenscenes: stride must be >= 1, got {stride}")
    require_empty(dst)
    found = sorted((int(m.group(1)), p) for p in src.glob("frame-*.depth.png") if (m := _FRAME.search(p.name)))
    if not found:
        raise InputError(f"import_sevenscenes: {src} has no frame-<i>.depth.png images")
    picked = found[::stride]
    cam = _read_intrinsics(src, picked[0][1])
    feature_dir = Path(features) if features is not None else None
    mask_dir = Path(masks) if masks is not None else None

    def optional(folder: Path | None, index: int, exts: tuple[str, ...]) -> Path | None:
        return None if folder is None else _first_file(folder, (str(index), f"{index:06d}"), exts)

    feature_files = {i: optional(feature_dir, i, (".npy",)) for i, _ in picked}
    present = [p for p in feature_files.values() if p is not None]
    if present:
        dim = int(np.load(present[0], mmap_mode="r").shape[-1])
    elif placeholder_maps:
        if vocabulary is not None:
            raise InputError(
                "import_sevenscenes: a vocabulary cannot be used with placeholder maps (their features mean "
                "nothing); leave it out, or pass feature maps of the vocabulary's space"
            )
        dim, feature_space, vocabulary = PLACEHOLDER_DIM, PLACEHOLDER_SPACE, placeholder_vocabulary()
    else:  # no maps: panogs run --masks-model ... --features-model ... computes them from the colour frames
        if vocabulary is not None and vocabulary.embeddings is not None:
            raise InputError(
                "import_sevenscenes: the vocabulary has embeddings but there are no feature maps whose space they "
                "would be in; leave the embeddings out (the run embeds the names with the features model)"
            )
        dim = None
    label = name or src.name
    with staged(dst) as stage:  # a failure part way leaves nothing at dst
        writer = BundleWriter(
            stage,
            name=f"{label} (placeholder maps)" if not present and placeholder_maps else label,
            camera=cam,
            depth_scale=SEVENSCENES_DEPTH_SCALE,
            feature_dim=dim,
            feature_space=feature_space if dim is not None else None,
        )
        if vocabulary is not None:
            writer.write_vocabulary(vocabulary)
        invalid, missing = [], []
        without_features = without_masks = 0
        for done, (index, depth_path) in enumerate(picked, start=1):
            fid = f"{index:06d}"
            pose = read_matrix(src / f"frame-{index:06d}.pose.txt")
            if pose is None:
                missing.append(fid)
            elif pose.shape != (4, 4) or not is_rigid(pose):
                invalid.append(fid)
            else:
                raw = _read_image(depth_path)
                if raw.ndim != 2 or raw.dtype != np.uint16 or raw.shape != (cam.height, cam.width):
                    size = f"{cam.width}x{cam.height}"
                    raise InputError(f"import_sevenscenes: {depth_path}: expected a {size} 16-bit PNG")
                raw = np.where(raw == _NO_DEPTH, 0, raw)
                color = _first_file(src, (f"frame-{index:06d}.color",), (".jpg", ".png"))
                feat_path, mask_path = feature_files[index], optional(mask_dir, index, (".png",))
                feat = None if feat_path is None else np.load(feat_path, allow_pickle=False).astype(np.float32)
                mask = None if mask_path is None else _read_image(mask_path).astype(np.int64)
                if not present and placeholder_maps and dim is not None and writer.num_frames == 0:
                    feat = np.full((1, 1, dim), 1.0 / np.sqrt(dim), np.float32)
                    mask = np.ones((cam.height, cam.width), np.int64)
                writer.add_frame(
                    fid, pose, raw.astype(np.float64) / SEVENSCENES_DEPTH_SCALE, color=color, features=feat, masks=mask
                )
                without_features += feat is None
                without_masks += mask is None
            report(on_progress, done, len(picked))
        if writer.num_frames == 0:
            raise InputError(f"import_sevenscenes: no usable frame among {len(picked)} (all lack a valid pose)")
        _record_left_out(writer, src, found, {index for index, _ in picked})
        writer.close()
    result = ImportReport(
        bundle=dst,
        frames_written=writer.num_frames,
        frames_skipped_invalid_pose=tuple(invalid),
        frames_skipped_missing=tuple(missing),
        frames_without_features=without_features,
        frames_without_masks=without_masks,
    )
    logger.info("import_sevenscenes: %s", result.summary())
    return result


def _record_left_out(writer: BundleWriter, src: Path, found: list[tuple[int, Path]], picked: set[int]) -> None:
    """The frames the stride left out, by their pose only (``skipped_frames``), so that ``panogs render RUN --frame
    ID`` reaches every frame of the sequence. No gravity ``up``: 7-Scenes' world (KinectFusion's) is not documented as
    gravity-aligned, so the pipeline estimates it."""
    for index, _ in found:
        if index in picked:
            continue
        pose = read_matrix(src / f"frame-{index:06d}.pose.txt")
        if pose is not None and pose.shape == (4, 4) and is_rigid(pose):
            writer.add_skipped_frame(f"{index:06d}", pose)


def _read_intrinsics(src: Path, first_depth: Path) -> Camera:
    path = src / "camera-intrinsics.txt"
    K = read_matrix(path)
    if K is None or K.shape not in ((3, 3), (4, 4)) or not np.all(np.isfinite(K[:3, :3])):
        raise InputError(f"import_sevenscenes: {path} missing or not a 3x3 matrix")
    depth = _read_image(first_depth)
    height, width = depth.shape[:2]
    fx, fy, cx, cy = (float(K[r, c]) for r, c in ((0, 0), (1, 1), (0, 2), (1, 2)))
    return Camera(width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy)


def _first_file(folder: Path, stems: tuple[str, ...], exts: tuple[str, ...]) -> Path | None:
    for stem in stems:
        for ext in exts:
            if (folder / f"{stem}{ext}").is_file():
                return folder / f"{stem}{ext}"
    return None


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"import_sevenscenes: {path}: does not decode as an image")
    return image
