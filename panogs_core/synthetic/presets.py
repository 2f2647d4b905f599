"""Sizes (presets) and degradation levels (difficulties) of synthetic scenes.

A :class:`SyntheticSpec` fixes how big a scene is (room, point count, frames, image sizes); a
:class:`Difficulty` fixes how imperfect its sensors and 2D models are (depth noise, feature noise, mask
errors, trajectory jitter). Both are frozen dataclasses; benches derive variants with ``dataclasses.replace``.
The numbers are documented in ``docs/synthetic.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from panogs_core.errors import ConfigError

Range = tuple[float, float]


def _check_range(name: str, value: Range, low: float = 0.0) -> None:
    if not (low <= value[0] <= value[1]):
        raise ConfigError(f"{name}: expected {low} <= min <= max, got {value}")


@dataclass(frozen=True, kw_only=True)
class SyntheticSpec:
    """Size of a synthetic scene.

    Attributes:
        name: Preset name, also the default scene name prefix.
        width: Camera width in pixels.
        height: Camera height in pixels.
        hfov_deg: Horizontal field of view in degrees (square pixels).
        feature_stride: Feature maps are ``(height // stride, width // stride)`` cells.
        num_frames: Depth frames on the trajectory.
        key_frame_stride: Every this-many-th frame gets features and masks (1 = every frame is a key frame).
        num_points: Target number of surface points of ``geometry.ply`` (the spacing follows from the area).
        room_length: Range of the longer room side, metres.
        room_width: Range of the shorter room side, metres.
        room_height: Range of the ceiling height, metres.
        zone_length: Rooms longer than this are split into furnished zones of about this length, metres.
        feature_space: Default text-embedding space of the features.
        realistic: A real-capture-like scene (``docs/synthetic.md``, preset ``scan``): a furnished studio with
            clutter and unannotated ground truth (``scan_layout.py``), a dense handheld trajectory of which
            only every ``dense_factor``-th pose is written, geometry from every dense pose, no coverage help,
            and the difficulty's strengths from :data:`REALISTIC_DIFFICULTIES`.
        dense_factor: Dense trajectory poses per written frame (realistic only). The geometry holds what any
            dense pose observes, as a real mesh is fused from every frame of the video while only a sparse
            subset are exported; written frames are every ``dense_factor``-th pose.
        unannotated_stuff: Fraction of the wall and floor points whose ground truth is left unannotated
            (-1), in blobs, as annotators of a real capture skip segments (realistic only).
        high_windows: Thin windows set into the walls at 1.5-2.1 m, above most views of the downward-looking key
            frames (realistic only; 0 = none, and the room is drawn as without the field).
        room_kind: What the realistic room is furnished as: ``studio`` (``scan_layout.build_scan_layout``'s
            three zones) or ``bathroom`` (a small room crowded with fixtures and cabinets, each seen by few key
            frames).
        invalid_poses: Key frames lost as a real capture loses them (realistic only): a run of this many
            consecutive key frames, and the frames between them, whose tracking failed; an importer drops a frame
            with a non-finite pose (``io.importers.common``), so the bundle holds none of them, while the mesh,
            fused from every frame, keeps what they saw.
    """

    name: str
    width: int = 320
    height: int = 240
    hfov_deg: float = 66.0
    feature_stride: int = 4
    num_frames: int = 40
    key_frame_stride: int = 1
    num_points: int = 50_000
    room_length: Range = (5.5, 7.0)
    room_width: Range = (4.2, 5.2)
    room_height: Range = (2.5, 2.8)
    zone_length: float = 4.5
    feature_space: str = "minilm-l6"
    realistic: bool = False
    dense_factor: int = 1
    unannotated_stuff: float = 0.0
    high_windows: int = 0
    room_kind: str = "studio"
    invalid_poses: int = 0

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"camera {self.width}x{self.height}: expected at least 16x16 pixels")
        if not 20.0 <= self.hfov_deg <= 120.0:
            raise ConfigError(f"hfov_deg: expected 20-120 degrees, got {self.hfov_deg}")
        if self.feature_stride < 1 or self.height // self.feature_stride < 2:
            raise ConfigError(f"feature_stride {self.feature_stride} leaves no feature map")
        if self.num_frames < 1 or self.key_frame_stride < 1:
            raise ConfigError("num_frames and key_frame_stride must be >= 1")
        if self.num_points < 100:
            raise ConfigError(f"num_points: expected >= 100, got {self.num_points}")
        _check_range("room_length", self.room_length, 2.5)
        _check_range("room_width", self.room_width, 2.5)
        _check_range("room_height", self.room_height, 2.2)
        if self.zone_length < 3.0:
            raise ConfigError(f"zone_length: expected >= 3 m, got {self.zone_length}")
        if self.dense_factor < 1:
            raise ConfigError(f"dense_factor: expected >= 1, got {self.dense_factor}")
        if not 0.0 <= self.unannotated_stuff < 1.0:
            raise ConfigError(f"unannotated_stuff: expected a fraction in [0, 1), got {self.unannotated_stuff}")
        if not 0 <= self.high_windows <= 8:
            raise ConfigError(f"high_windows: expected 0-8, got {self.high_windows}")
        if self.room_kind not in ("studio", "bathroom"):
            raise ConfigError(f"room_kind: expected 'studio' or 'bathroom', got {self.room_kind!r}")
        key_frames = -(-self.num_frames // self.key_frame_stride)
        if not 0 <= self.invalid_poses < key_frames:
            raise ConfigError(f"invalid_poses: expected 0 to {key_frames - 1} (key frames), got {self.invalid_poses}")


@dataclass(frozen=True, kw_only=True)
class DepthNoise:
    """Depth sensor model.

    Attributes:
        sigma_base_m: Constant part of the Gaussian depth noise, metres.
        sigma_quad: Depth-squared part: sigma(z) = sigma_base_m + sigma_quad * z**2 (z in metres).
        dropout: Fraction of pixels dropped at random (value 0).
        hole_fraction: Fraction of the image covered by smooth blob-shaped holes.
        edge_dropout: Probability that a pixel on a depth discontinuity (> 10 cm jump) is dropped.
        max_depth_m: Depth beyond this is missing (0).
    """

    sigma_base_m: float = 0.001
    sigma_quad: float = 0.002
    dropout: float = 0.01
    hole_fraction: float = 0.02
    edge_dropout: float = 0.3
    max_depth_m: float = 7.0


@dataclass(frozen=True, kw_only=True)
class FeatureNoise:
    """2D language-feature model.

    Every sigma is per dimension, in units of the class's median distance to the other classes
    (``catalog.class_noise_scale``); ``instance_spread`` is a length in the same unit.

    Attributes:
        instance_spread: Length of the fixed perturbation of each instance's direction (shared by all its
            views), not per dimension: a per-dimension sigma grows with sqrt(D) and gave two chairs of a
            384-d scene feature cosines near 0.2, an instance fingerprint that real LSeg / OpenSeg maps do not
            have (instances of one class look alike to them; telling them apart is the masks' job).
        view_sigma: Extra perturbation of each instance per frame (view-dependent appearance).
        pixel_sigma: Independent noise per feature-map cell.
        confused_instances: Fraction of instances that lean towards a confusable class.
        confusion_weight: Range of the lean (0 = own class, 1 = the other class; > 0.5 flips the argmax).
        confused_area: Fraction of each frame covered by smooth blobs that lean towards a confusable class.
        area_weight: Lean inside those blobs.
        blur_cells: Gaussian blur of the feature map after area averaging, in cells (0 = none).
        anchored_area: Fraction of the surface inside confusion regions fixed in the world (0 = off): spheres
            where a class with related classes (``catalog.RELATED``) leans towards one of them in every view,
            so that multi-view fusion cannot average the error away (realistic scenes only).
        anchored_weight: Range of the lean inside an anchored region (drawn per region).
        anchored_radius_m: Range of the anchored regions' radii, metres.
    """

    instance_spread: float = 0.25
    view_sigma: float = 0.08
    pixel_sigma: float = 0.18
    confused_instances: float = 0.1
    confusion_weight: Range = (0.25, 0.55)
    confused_area: float = 0.04
    area_weight: float = 0.6
    blur_cells: float = 0.5
    anchored_area: float = 0.0
    anchored_weight: Range = (0.5, 0.8)
    anchored_radius_m: Range = (0.25, 0.6)


@dataclass(frozen=True, kw_only=True)
class MaskNoise:
    """SAM-like 2D instance mask model (rates are per instance and frame unless stated).

    Attributes:
        stuff_split: Probability that a wall / floor / ceiling piece is split into several masks.
        stuff_pieces: Range of the number of pieces of a split stuff region.
        part_split: Probability that an object is split into its parts (boxes, or faces of a single box).
        merge_touching: Probability that two objects touching in 3D and adjacent in the image share one mask.
        merge_any: Probability that any two adjacent regions share one mask.
        jitter_px: Amplitude of the smooth boundary displacement, pixels.
        gap_px: Width of the unlabelled band left along mask boundaries, pixels.
        min_area: Masks smaller than this fraction of the image are dropped (0 = no mask).
        miss: Probability that a mask is dropped entirely.
    """

    stuff_split: float = 0.5
    stuff_pieces: tuple[int, int] = (2, 4)
    part_split: float = 0.3
    merge_touching: float = 0.15
    merge_any: float = 0.0
    jitter_px: float = 1.5
    gap_px: int = 1
    min_area: float = 0.001
    miss: float = 0.05


@dataclass(frozen=True, kw_only=True)
class TrajectoryNoise:
    """Handheld camera imperfection.

    Attributes:
        position_m: Gaussian position jitter, metres.
        rotation_deg: Gaussian roll / pitch / yaw jitter, degrees.
        uneven: Spread of the step lengths along the path (0 = equal steps; 1 = gamma-distributed bursts).
        pose_error_m: Gaussian error of the written poses against the ones rendered, metres per axis (0 =
            off): a real capture's poses come from its own registration and are off by a little per frame.
        pose_error_deg: The same for the rotation, degrees per axis.
    """

    position_m: float = 0.02
    rotation_deg: float = 1.5
    uneven: float = 0.3
    pose_error_m: float = 0.0
    pose_error_deg: float = 0.0


@dataclass(frozen=True, kw_only=True)
class Difficulty:
    """One degradation level: all sensor and 2D-model imperfections together."""

    name: str
    depth: DepthNoise = field(default_factory=DepthNoise)
    features: FeatureNoise = field(default_factory=FeatureNoise)
    masks: MaskNoise = field(default_factory=MaskNoise)
    trajectory: TrajectoryNoise = field(default_factory=TrajectoryNoise)
    color_noise: float = 0.02  # std of per-pixel RGB noise, in [0, 1] units


PRESETS: dict[str, SyntheticSpec] = {
    "tiny": SyntheticSpec(
        name="tiny", width=160, height=120, feature_stride=2, num_frames=12, num_points=12_000,
        room_length=(3.8, 4.6), room_width=(3.2, 3.8), room_height=(2.4, 2.6),
    ),
    "small": SyntheticSpec(name="small", num_frames=30, num_points=40_000, room_length=(4.5, 5.5),
                           room_width=(3.6, 4.4)),
    "default": SyntheticSpec(name="default"),
    "large": SyntheticSpec(
        name="large", num_frames=120, num_points=152_000, room_length=(10.0, 12.0), room_width=(7.0, 8.5),
        room_height=(2.7, 3.0), zone_length=3.6, feature_space="clip-vit-b32",
    ),
    # Like the held-out real ScanNet capture (docs/synthetic.md, "The scan preset"): 58 degree depth
    # camera at half its 640x480, feature maps a quarter of that, 1400 dense poses of which 140 are written
    # and 70 (every 20th pose, as the real key frames) are key frames, CLIP features; 80k surface samples of
    # which 45-51k are observed; 22 % of the wall and floor unannotated.
    "scan": SyntheticSpec(
        name="scan", hfov_deg=58.0, num_frames=140, key_frame_stride=2, num_points=80_000,
        room_length=(7.0, 7.8), room_width=(5.4, 6.2), room_height=(2.5, 2.7), feature_space="clip-vit-b32",
        realistic=True, dense_factor=10, unannotated_stuff=0.22,
    ),
    # The scan room at the real capture's size, for the speed benchmark: 640x480 depth and masks, feature maps a
    # quarter of that (160x120), 2000 dense poses of which 200 are written and 100 are key frames, 135k surface
    # samples of which about 80k are observed (docs/synthetic.md, "The scannet-size preset").
    "scannet-size": SyntheticSpec(
        name="scannet-size", width=640, height=480, hfov_deg=58.0, num_frames=200, key_frame_stride=2,
        num_points=135_000, room_length=(7.0, 7.8), room_width=(5.4, 6.2), room_height=(2.5, 2.7),
        feature_space="clip-vit-b32", realistic=True, dense_factor=10, unannotated_stuff=0.22,
    ),
    # The scan room with thin objects in the walls mostly outside every key view: 3 windows set flush into the walls
    # at 1.5-2.1 m (docs/synthetic.md, "Thin objects in walls"); the rest of the room as `scan` draws it.
    "scan-walls": SyntheticSpec(
        name="scan-walls", hfov_deg=58.0, num_frames=140, key_frame_stride=2, num_points=80_000,
        room_length=(7.0, 7.8), room_width=(5.4, 6.2), room_height=(2.5, 2.7), feature_space="clip-vit-b32",
        realistic=True, dense_factor=10, unannotated_stuff=0.22, high_windows=3,
    ),
    # A bathroom like the held-out real one (docs/synthetic.md, "The bathroom"): a 3.0-3.6 x 2.5-2.8 m room with a
    # bathtub, toilet, vanity, sink, cabinets and shelves (10-13 objects), 40 written frames of which 20 are key
    # frames, two of them lost to invalid poses; the surface at the scan room's spacing.
    "scan-bath": SyntheticSpec(
        name="scan-bath", hfov_deg=58.0, num_frames=40, key_frame_stride=2, num_points=26_000,
        room_length=(3.0, 3.6), room_width=(2.5, 2.8), room_height=(2.4, 2.6), feature_space="clip-vit-b32",
        realistic=True, dense_factor=10, unannotated_stuff=0.22, room_kind="bathroom", invalid_poses=2,
    ),
}  # fmt: skip

DIFFICULTIES: dict[str, Difficulty] = {
    "easy": Difficulty(
        name="easy",
        depth=DepthNoise(sigma_base_m=0.0005, sigma_quad=0.0005, dropout=0.002, hole_fraction=0.0,
                         edge_dropout=0.05, max_depth_m=10.0),
        features=FeatureNoise(instance_spread=0.1, view_sigma=0.025, pixel_sigma=0.07,
                              confused_instances=0.0, confused_area=0.0, blur_cells=0.0),
        masks=MaskNoise(stuff_split=0.0, part_split=0.05, merge_touching=0.02, jitter_px=0.5, gap_px=0,
                        min_area=0.0005, miss=0.0),
        trajectory=TrajectoryNoise(position_m=0.01, rotation_deg=0.5, uneven=0.1),
        color_noise=0.01,
    ),
    "default": Difficulty(name="default"),
    "hard": Difficulty(
        name="hard",
        depth=DepthNoise(sigma_base_m=0.002, sigma_quad=0.005, dropout=0.04, hole_fraction=0.06,
                         edge_dropout=0.6, max_depth_m=4.5),
        features=FeatureNoise(instance_spread=0.4, view_sigma=0.1, pixel_sigma=0.25,
                              confused_instances=0.25, confusion_weight=(0.3, 0.7), confused_area=0.1,
                              area_weight=0.65, blur_cells=1.0),
        masks=MaskNoise(stuff_split=0.8, stuff_pieces=(3, 6), part_split=0.5, merge_touching=0.3,
                        merge_any=0.05, jitter_px=3.0, gap_px=2, min_area=0.002, miss=0.1),
        trajectory=TrajectoryNoise(position_m=0.04, rotation_deg=3.0, uneven=1.0),
        color_noise=0.04,
    ),
}  # fmt: skip


def _realistic(base: Difficulty, trajectory: dict[str, float], features: dict[str, object]) -> Difficulty:
    """A difficulty of :data:`DIFFICULTIES` with the realism strengths switched on (see below)."""
    return replace(
        base,
        features=replace(base.features, **features),  # type: ignore[arg-type]
        trajectory=replace(base.trajectory, **trajectory),
    )


# The difficulties of a realistic spec (preset ``scan``): the sensor models of DIFFICULTIES, with world-anchored
# confusions, more confused instances, a realistic blur of the quarter-resolution feature maps and pose errors,
# calibrated so that the fused-feature argmax baseline lands near the real capture's mIoU (docs/synthetic.md).
REALISTIC_DIFFICULTIES: dict[str, Difficulty] = {
    "easy": _realistic(
        DIFFICULTIES["easy"],
        trajectory={"pose_error_m": 0.0, "pose_error_deg": 0.0},
        features={"blur_cells": 0.0, "anchored_area": 0.0},
    ),
    "default": _realistic(
        DIFFICULTIES["default"],
        trajectory={"pose_error_m": 0.01, "pose_error_deg": 0.4},
        features={"confused_instances": 0.12, "confusion_weight": (0.35, 0.75), "blur_cells": 0.7,
                  "anchored_area": 0.07, "anchored_weight": (0.55, 0.85)},
    ),
    "hard": _realistic(
        DIFFICULTIES["hard"],
        trajectory={"pose_error_m": 0.02, "pose_error_deg": 0.7},
        features={"confused_instances": 0.22, "confusion_weight": (0.4, 0.8), "blur_cells": 1.0,
                  "anchored_area": 0.17, "anchored_weight": (0.55, 0.9)},
    ),
}  # fmt: skip


def get_preset(preset: str | SyntheticSpec) -> SyntheticSpec:
    """The spec of a preset name (or the spec itself).

    Raises:
        ConfigError: for an unknown preset name.
    """
    if isinstance(preset, SyntheticSpec):
        return preset
    if preset not in PRESETS:
        raise ConfigError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
    return PRESETS[preset]


def get_difficulty(difficulty: str | Difficulty, realistic: bool = False) -> Difficulty:
    """The degradation level of a difficulty name (or the level itself).

    Args:
        difficulty: ``easy``, ``default``, ``hard`` or a :class:`Difficulty` (returned as is).
        realistic: Look a name up in :data:`REALISTIC_DIFFICULTIES` (for a realistic spec) rather than in
            :data:`DIFFICULTIES`.

    Raises:
        ConfigError: for an unknown difficulty name.
    """
    if isinstance(difficulty, Difficulty):
        return difficulty
    table = REALISTIC_DIFFICULTIES if realistic else DIFFICULTIES
    if difficulty not in table:
        raise ConfigError(f"difficulty: expected one of {sorted(table)}, got {difficulty!r}")
    return table[difficulty]
