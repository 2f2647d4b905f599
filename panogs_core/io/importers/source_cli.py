"""The text of ``panogs import <source>`` for the capture importers: per source a line of help, a description, an
example and its options (flag, options field, type, default, help). Kept apart from :mod:`.sources` (which pairs
each with its importer) because the command line reads it to build its parsers, and ``panogs --help`` must not
load the importers' numeric libraries."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class CliOption:
    """One option of ``panogs import <source>``: its flag, the options field it sets, and its help.

    ``field`` names a field of the source's options dataclass, or ``selection.<f>`` / ``maps.<f>`` for the shared
    ones. ``kind`` is the value's type: ``path`` a file or folder, ``switch`` a flag that sets True,
    ``switch_off`` a flag that sets False (``--no-ply``). ``--vocabulary`` takes a name or a file that the command
    line resolves to a :class:`Vocabulary` before :func:`options_from_values`.
    """

    flag: str
    field: str
    kind: Literal["int", "float", "str", "path", "switch", "switch_off"]
    default: object
    help: str
    choices: tuple[object, ...] = ()


@dataclass(frozen=True)
class SourceCli:
    """What ``panogs import <source>`` needs: one line of help, a description, an example and the options."""

    name: str
    help: str
    description: str
    example: str
    options: tuple[CliOption, ...]


SHARED_OPTIONS = (
    CliOption("--stride", "selection.stride", "int", 1, "keep every n-th frame"),
    CliOption(
        "--min-translation",
        "selection.min_translation",
        "float",
        0.0,
        "metres: keep a frame only when it moved more than this (or turned more than --min-rotation) since the "
        "last kept one; 0 leaves translation out of the rule, and both 0 keep every frame",
    ),
    CliOption(
        "--min-rotation",
        "selection.min_rotation",
        "float",
        0.0,
        "degrees: see --min-translation; 0 leaves rotation out of the rule",
    ),
    CliOption("--max-frames", "selection.max_frames", "int", None, "at most this many frames, spread evenly"),
    CliOption("--features", "maps.features", "path", None, "folder of <frame>.npy (Hf, Wf, D) feature maps"),
    CliOption("--masks", "maps.masks", "path", None, "folder of <frame>.png instance-id masks"),
    CliOption("--feature-space", "maps.feature_space", "str", "clip-vit-b32", "features.space of the feature maps"),
    CliOption(
        "--placeholder-maps",
        "maps.placeholder_maps",
        "switch",
        False,
        "without --features: a constant feature map and a one-segment mask on the first frame, enough to fit "
        "and render (labels mean nothing). Without --features nor this, the bundle has no maps and panogs run "
        "--masks-model ... --features-model ... computes them",
    ),
    CliOption("--vocabulary", "maps.vocabulary", "str", None, "scannet20 | matterport21 | path to vocabulary.json"),
    CliOption("--name", "name", "str", None, "scene name (default: the source folder's)"),
)


NERFSTUDIO_CLI = SourceCli(
    name="nerfstudio",
    help="a nerfstudio data folder (transforms.json with depth: Polycam, Record3D via ns-process-data)",
    description="transform_matrix in OpenGL camera axes, 16-bit depth PNGs (millimetres by default), pinhole "
    "intrinsics at the top level or per frame; distortion is refused; ply_file_path becomes the geometry",
    example="panogs import nerfstudio polycam_processed/ bundles/living_room --placeholder-maps --max-frames 300",
    options=(
        CliOption("--depth-unit", "depth_unit", "float", 0.001, "metres per depth PNG value (0.001: millimetres)"),
        CliOption("--no-ply", "use_ply", "switch_off", True, "ignore ply_file_path (primitives from the depth)"),
        *SHARED_OPTIONS,
    ),
)
RECORD3D_CLI = SourceCli(
    name="record3d",
    help="an iPhone / iPad LiDAR capture: Record3D's EXR + JPG export",
    description="rgb/<n>.jpg, depth/<n>.exr (metres, 256x192), metadata.json (K column-major, ARKit poses); the "
    "bundle camera is the depth camera, colour is resampled; low-confidence depth is cleared",
    example="panogs import record3d ~/Record3D/2026-05-01--10-12-44 bundles/kitchen --placeholder-maps "
    "--min-translation 0.05 --min-rotation 5",
    options=(
        CliOption(
            "--min-confidence",
            "min_confidence",
            "int",
            1,
            "clear depth whose ARKit confidence is below this (0 low, 1 medium, 2 high; 0 keeps all)",
            (0, 1, 2),
        ),
        *SHARED_OPTIONS,
    ),
)
TUM_CLI = SourceCli(
    name="tum",
    help="a TUM RGB-D sequence (rgb.txt, depth.txt, groundtruth.txt), as many SLAM tools write",
    description="frames associated by nearest timestamp, depth / 5000; intrinsics from --intrinsics FILE or "
    "--camera (the dataset's published Freiburg calibrations), one of them required",
    example="panogs import tum rgbd_dataset_freiburg1_desk bundles/fr1_desk --camera freiburg1 --placeholder-maps "
    "--stride 5",
    options=(
        CliOption("--intrinsics", "intrinsics", "path", None, "text file 'fx fy cx cy' of the depth camera"),
        CliOption(
            "--camera",
            "camera",
            "str",
            None,
            "a Freiburg camera instead of --intrinsics",
            ("freiburg1", "freiburg2", "freiburg3"),
        ),
        CliOption("--max-time-difference", "max_time_difference", "float", 0.02, "seconds between associated stamps"),
        CliOption("--depth-scale", "depth_scale", "float", 5000.0, "depth PNG value per metre"),
        *SHARED_OPTIONS,
    ),
)
CAPTURE_CLIS: tuple[SourceCli, ...] = (NERFSTUDIO_CLI, RECORD3D_CLI, TUM_CLI)
