"""The appearance fit: it improves the renders, skips frames without colour, obeys cancellation and its settings."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture)

from panogs_core.errors import Cancelled, ConfigError
from panogs_core.gaussians import fit_appearance
from panogs_core.gaussians.config import (
    CPU_COARSE_FRACTION,
    CPU_FIT_WIDTH,
    CPU_ITERATIONS,
    GPU_ITERATIONS,
    AppearanceConfig,
    GaussianScene,
    resolve_schedule,
)
from panogs_core.gaussians.rasterizer import Gaussians3D, PinholeCamera, rasterize
from panogs_core.io.bundle import open_bundle
from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.snapshots import StageSnapshot
from panogs_core.stages.primitives import gaussian_log_scales
from panogs_core.types import Camera

CAMERA = Camera(width=48, height=36, fx=40.0, fy=40.0, cx=23.5, cy=17.5)
SPACING = 0.04  # m between the wall's points
# A bundle needs features and masks on some frame; the fit reads neither.
_EXTRAS = {"features": np.zeros((4, 4, 4), np.float32), "masks": np.ones((CAMERA.height, CAMERA.width), np.int32)}


def _wall() -> tuple[np.ndarray, np.ndarray]:
    """A 24 x 18 grid of points on the plane z = 1.5 with a colour pattern (stripes and a gradient)."""
    xs, ys = np.meshgrid(np.arange(24) * SPACING - 0.46, np.arange(18) * SPACING - 0.34)
    points = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 1.5)], axis=1).astype(np.float32)
    stripes = (np.arange(xs.size) // 3) % 2
    colors = np.stack([0.2 + 0.6 * stripes, np.linspace(0.1, 0.9, xs.size), 0.5 - 0.3 * stripes], 1)
    return points, colors.astype(np.float32)


def _pose(dx: float, dy: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (dx, dy, 0.0)
    return pose


def _true_image(points: np.ndarray, colors: np.ndarray, pose: np.ndarray) -> np.ndarray:  # (H, W, 3) uint8
    """What the camera sees: opaque Gaussians as wide as the point spacing (the 'truth' the fit must approach)."""
    n = len(points)
    g = Gaussians3D(
        means=torch.tensor(points),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        log_scales=torch.full((n, 3), math.log(SPACING * 0.6)),
        opacity_logits=torch.full((n,), 4.0),
    )
    c = CAMERA
    cam = PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, torch.tensor(pose))
    img = rasterize(g, torch.tensor(colors), cam).features.clamp(0, 1)
    return (img.numpy() * 255).round().astype(np.uint8)


@pytest.fixture(scope="module")
def wall_bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    points, colors = _wall()
    root = tmp_path_factory.mktemp("wall") / "bundle"
    with BundleWriter(root, name="wall", camera=CAMERA, feature_dim=4, feature_space="test", color_format="png") as w:
        for i, (dx, dy) in enumerate([(0, 0), (0.05, 0), (-0.05, 0.02), (0.02, -0.04), (0.0, 0.03)]):
            pose = _pose(dx, dy)
            depth = np.full((CAMERA.height, CAMERA.width), 1.5, np.float32)
            w.add_frame(f"{i:03d}", pose, depth, color=_true_image(points, colors, pose), **_EXTRAS)
        w.add_frame("nocolor", _pose(0.01, 0.01), np.full((CAMERA.height, CAMERA.width), 1.5, np.float32))
        w.write_geometry(points, colors=np.full_like(colors, 0.5))  # the geometry's colour is wrong: grey
    return root


def _prims(points: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(
        points=points,
        scales=gaussian_log_scales(points),  # the primitives stage's initialisation
        opacities=np.zeros(len(points), np.float32),
    )


def _fit(bundle: Path, **settings: object) -> GaussianScene:
    points, _ = _wall()
    scene = open_bundle(bundle)
    cfg = AppearanceConfig(**{"iterations": 40, "fit_width": 48, "device": "cpu", **settings})  # type: ignore[arg-type]
    return fit_appearance(scene, _prims(points), np.full((len(points), 3), 0.5, np.float32), cfg)


@pytest.mark.slow  # 40 fit iterations with PSNR before and after (2-4 s here)
def test_the_fit_raises_psnr_and_skips_frames_without_colour(wall_bundle: Path) -> None:
    steps: list[tuple[int, int]] = []
    points, _ = _wall()
    scene = open_bundle(wall_bundle)
    cfg = AppearanceConfig(iterations=40, fit_width=48, device="cpu")
    fitted = fit_appearance(
        scene,
        _prims(points),
        np.full((len(points), 3), 0.5, np.float32),
        cfg,
        on_progress=lambda d, t: steps.append((d, t)),
    )
    assert fitted.fitted
    assert fitted.psnr_before is not None
    assert fitted.psnr_after is not None
    assert fitted.psnr_after > fitted.psnr_before + 3.0
    assert fitted.ssim_after is not None
    assert fitted.ssim_before is not None
    assert fitted.ssim_after > fitted.ssim_before
    assert fitted.skipped_frames == ("nocolor",)
    assert "without colour" in fitted.note
    assert steps[-1] == (40, 40)
    assert len(steps) == 40
    assert np.allclose(fitted.means, points)  # centres fixed by default
    assert np.allclose(np.linalg.norm(fitted.quats, axis=1), 1.0, atol=1e-5)
    assert float(fitted.opacity_logits.mean()) > 0.5  # the wall is opaque: opacities stay high


def test_the_cpu_fit_runs_on_its_threads_and_restores_them(wall_bundle: Path) -> None:
    points, _ = _wall()
    seen: list[int] = []
    torch.set_num_threads(2)
    try:
        fit_appearance(
            open_bundle(wall_bundle),
            _prims(points),
            np.full((len(points), 3), 0.5, np.float32),
            AppearanceConfig(iterations=2, fit_width=24, device="cpu", cpu_threads=1),
            on_progress=lambda d, t: seen.append(torch.get_num_threads()),
        )
        assert seen == [1, 1]
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)  # the module's fixture setting


def test_held_out_frames_are_not_fitted_but_scored(wall_bundle: Path) -> None:
    fitted = _fit(wall_bundle, held_out_every=2, iterations=10)
    assert fitted.evaluated_on == "held-out"


def test_centres_move_within_the_radius_when_allowed(wall_bundle: Path) -> None:
    points, _ = _wall()
    fitted = _fit(wall_bundle, move_centres=True, max_centre_offset=0.002, lr_position=1.0, iterations=10)
    moved = np.linalg.norm(fitted.means - points, axis=1)
    assert moved.max() <= 0.002 + 1e-6
    assert moved.max() > 1e-4


def test_coarse_to_fine_renders_the_first_iterations_at_half_the_width(wall_bundle: Path) -> None:
    from panogs_core.gaussians import initialise, split_frames
    from panogs_core.gaussians.fit import Fitter

    points, _ = _wall()
    scene = open_bundle(wall_bundle)
    cfg = AppearanceConfig(iterations=6, fit_width=48, device="cpu", coarse_fraction=0.5)
    frames = split_frames(scene, cfg)[0]
    start = initialise(scene, _prims(points), np.full((len(points), 3), 0.5, np.float32), frames, cfg)
    fitter = Fitter(scene, start, cfg, resolve_schedule(cfg, CAMERA.width, cuda=False))
    sizes = []
    for _ in range(6):
        fitter._step(frames)
        sizes.extend({size for _, size in fitter._targets})
        fitter._targets.clear()
    assert sizes == [(24, 18)] * 3 + [(48, 36)] * 3
    assert fitter.size == (48, 36)  # what the scores and the result see between steps
    assert fitter.render(frames[0], 0).shape == (36, 48, 3)


def test_cancellation_stops_the_fit(wall_bundle: Path) -> None:
    points, _ = _wall()
    scene = open_bundle(wall_bundle)

    def stop_at_three(done: int, total: int) -> None:
        if done == 3:
            raise Cancelled("stop")

    with pytest.raises(Cancelled):
        fit_appearance(
            scene,
            _prims(points),
            np.full((len(points), 3), 0.5, np.float32),
            AppearanceConfig(iterations=40, fit_width=24, device="cpu"),
            on_progress=stop_at_three,
        )


def test_a_bundle_without_colour_skips_the_stage_with_a_message(tmp_path: Path) -> None:
    points, _ = _wall()
    with BundleWriter(tmp_path / "b", name="grey", camera=CAMERA, feature_dim=4, feature_space="test") as w:
        w.add_frame("a", _pose(0, 0), np.full((CAMERA.height, CAMERA.width), 1.5, np.float32), **_EXTRAS)
        w.write_geometry(points)
    fitted = _fit(tmp_path / "b")
    assert not fitted.fitted
    assert "none of the 1 frames has a colour image" in fitted.note
    assert fitted.psnr_after is None


@pytest.mark.parametrize("initialisation", ["reference", "surface"])
def test_turned_off_returns_the_initialisation(wall_bundle: Path, initialisation: str) -> None:
    # Off, the stage returns the primitives' own initialisation whatever cfg.initialisation says: the pipeline
    # writes an unfitted scene from the primitives, so the surface initialisation would be work for nothing.
    points, _ = _wall()
    fitted = _fit(wall_bundle, enabled=False, initialisation=initialisation)
    assert not fitted.fitted
    assert "turned off" in fitted.note
    assert np.allclose(fitted.sh[:, 0], 0.0)  # grey: DC coefficient (0.5 - 0.5) / C0
    assert np.allclose(fitted.log_scales, gaussian_log_scales(points))


def test_the_surface_initialisation_is_flat_covering_and_takes_the_frames_colours(wall_bundle: Path) -> None:
    from panogs_core.gaussians import initialise, split_frames

    points, colors = _wall()
    scene, cfg = open_bundle(wall_bundle), AppearanceConfig(fit_width=48, device="cpu")  # the default: surface
    grey = np.full((len(points), 3), 0.5, np.float32)
    start = initialise(scene, _prims(points), grey, split_frames(scene, cfg)[0], cfg)
    assert not start.fitted
    scales = np.exp(start.log_scales)
    rot = np.stack([_rotation(q) for q in start.quats])
    assert np.allclose(np.abs(rot[:, 2, 2]), 1.0, atol=1e-3)  # the third axis is the wall's normal (z)
    assert np.all(scales[:, 2] < 0.3 * scales[:, 0])  # flat along the normal
    assert np.all(scales[:, 0] > 0.5 * SPACING)  # wide enough to cover the gaps
    assert float(1 / (1 + np.exp(-start.opacity_logits.min()))) > 0.85
    # the grey given colours are replaced by what the frames show (the truth up to the renders' blending)
    error = np.abs(start.dc_colors() - colors).mean()
    assert error < 0.1 < np.abs(0.5 - colors).mean()


def test_the_surface_initialisation_scores_higher_at_zero_iterations(wall_bundle: Path) -> None:
    surface = _fit(wall_bundle, iterations=1)
    reference = _fit(wall_bundle, iterations=1, initialisation="reference")
    assert surface.psnr_before is not None
    assert reference.psnr_before is not None
    assert surface.psnr_before > reference.psnr_before + 5.0


def test_exposure_compensation_is_learned_per_frame_and_left_out_of_the_result(wall_bundle: Path) -> None:
    with_it = _fit(wall_bundle, iterations=12, exposure_compensation=True)  # each frame seen twice
    without = _fit(wall_bundle, iterations=12)
    assert with_it.means.shape == without.means.shape
    assert not np.array_equal(with_it.sh, without.sh)  # the per-frame gains changed what the Gaussians learned


def _rotation(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_checkpoint_round_trip(wall_bundle: Path, tmp_path: Path) -> None:
    fitted = _fit(wall_bundle, iterations=3)
    fitted.save(tmp_path / "a.npz")
    back = GaussianScene.load(tmp_path / "a.npz")
    assert np.array_equal(back.sh, fitted.sh)
    assert np.array_equal(back.opacity_logits, fitted.opacity_logits)
    assert back.summary() == fitted.summary()


def test_default_schedule_depends_on_the_device() -> None:
    cpu = resolve_schedule(AppearanceConfig(), 640, cuda=False)
    gpu = resolve_schedule(AppearanceConfig(), 640, cuda=True)
    assert (cpu.device, cpu.iterations, cpu.fit_width) == ("cpu", CPU_ITERATIONS, CPU_FIT_WIDTH)
    assert (gpu.device, gpu.iterations, gpu.fit_width) == ("cuda", GPU_ITERATIONS, 640)
    # coarse to fine on the CPU only (full size throughout on a GPU, as 3DGS), and a share given is kept
    assert (cpu.coarse_fraction, gpu.coarse_fraction) == (CPU_COARSE_FRACTION, 0.0)
    assert resolve_schedule(AppearanceConfig(coarse_fraction=0.0), 640, cuda=False).coarse_fraction == 0.0
    assert resolve_schedule(AppearanceConfig(coarse_fraction=0.5), 640, cuda=True).coarse_fraction == 0.5
    assert resolve_schedule(AppearanceConfig(device="cpu"), 640, cuda=True).device == "cpu"
    # The CPU default fits its time budget: fewer iterations for more Gaussians, never fewer than the floor,
    # and iterations asked for are kept.
    assert resolve_schedule(AppearanceConfig(), 640, cuda=False, num_gaussians=20_000).iterations == CPU_ITERATIONS
    assert resolve_schedule(AppearanceConfig(), 640, cuda=False, num_gaussians=30_000).iterations == 146
    assert resolve_schedule(AppearanceConfig(), 640, cuda=False, num_gaussians=144_000).iterations == 30
    assert resolve_schedule(AppearanceConfig(), 640, cuda=False, num_gaussians=10**8).iterations == 10
    assert resolve_schedule(AppearanceConfig(iterations=300), 640, cuda=False, num_gaussians=10**6).iterations == 300
    assert resolve_schedule(AppearanceConfig(), 640, cuda=True, num_gaussians=10**6).iterations == GPU_ITERATIONS
    assert resolve_schedule(AppearanceConfig(fit_width=4000), 640, cuda=False).fit_width == 640
    with pytest.raises(ConfigError, match="no CUDA device"):
        resolve_schedule(AppearanceConfig(device="cuda"), 640, cuda=False)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("sh_degree", 4, "appearance.sh_degree"),
        ("iterations", 0, "appearance.iterations"),
        ("lr_opacity", -1.0, "appearance.lr_opacity"),
        ("device", "gpu", "appearance.device"),
        ("backend", "vulkan", "appearance.backend"),
        ("dssim_weight", 1.5, "appearance.dssim_weight"),
        ("coarse_fraction", -0.1, "appearance.coarse_fraction"),
        ("photometric_norm", "l3", "appearance.photometric_norm"),
    ],
)
def test_bad_settings_are_refused_naming_the_field(field: str, value: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        AppearanceConfig(**{field: value})  # type: ignore[arg-type]


class _StopAt:
    """A progress callback that raises ``error`` at iteration ``at`` and records every report."""

    def __init__(self, at: int | None, error: type[Cancelled] = Cancelled) -> None:
        self.at, self.error, self.seen = at, error, []  # type: ignore[var-annotated]

    def __call__(self, done: int, total: int) -> None:
        self.seen.append(done)
        if done == self.at:
            raise self.error("stop")


def _fit_with(bundle: Path, snapshot: StageSnapshot | None, progress: _StopAt) -> GaussianScene:
    points, _ = _wall()
    cfg = AppearanceConfig(iterations=12, fit_width=24, device="cpu")
    grey = np.full((len(points), 3), 0.5, np.float32)
    return fit_appearance(open_bundle(bundle), _prims(points), grey, cfg, on_progress=progress, snapshot=snapshot)


def test_a_cancelled_fit_resumes_from_its_snapshot_to_the_same_result(wall_bundle: Path, tmp_path: Path) -> None:
    whole = _fit_with(wall_bundle, None, _StopAt(None))
    snapshot = StageSnapshot(tmp_path / "appearance.partial.pt", key="k1")
    with pytest.raises(Cancelled):
        _fit_with(wall_bundle, snapshot, _StopAt(5))
    assert snapshot.path.is_file()
    resumed_progress = _StopAt(None)
    resumed = _fit_with(wall_bundle, snapshot, resumed_progress)
    assert resumed_progress.seen == list(range(6, 13)), "iterations 1-5 are not run again"
    for name in ("sh", "opacity_logits", "log_scales", "quats", "means"):
        assert np.array_equal(getattr(resumed, name), getattr(whole, name)), name
    assert resumed.psnr_before == whole.psnr_before
    assert resumed.psnr_after == whole.psnr_after


def test_a_snapshot_is_used_only_under_its_own_key_and_when_reading_is_allowed(
    wall_bundle: Path, tmp_path: Path
) -> None:
    path = tmp_path / "appearance.partial.pt"
    with pytest.raises(Cancelled):
        _fit_with(wall_bundle, StageSnapshot(path, key="old-settings"), _StopAt(5))
    for snapshot in (StageSnapshot(path, key="new-settings"), StageSnapshot(path, key="old-settings", readable=False)):
        progress = _StopAt(None)
        _fit_with(wall_bundle, snapshot, progress)
        assert progress.seen[0] == 1, "the fit started afresh"


def test_a_stop_that_must_write_nothing_leaves_no_snapshot(wall_bundle: Path, tmp_path: Path) -> None:
    class OwnerChanged(Cancelled):
        save_partial_work = False

    snapshot = StageSnapshot(tmp_path / "appearance.partial.pt", key="k1")
    with pytest.raises(OwnerChanged):
        _fit_with(wall_bundle, snapshot, _StopAt(5, OwnerChanged))
    assert not snapshot.path.exists()


def test_an_unreadable_snapshot_is_ignored(wall_bundle: Path, tmp_path: Path) -> None:
    snapshot = StageSnapshot(tmp_path / "appearance.partial.pt", key="k1")
    snapshot.path.write_bytes(b"cut short")
    progress = _StopAt(None)
    assert _fit_with(wall_bundle, snapshot, progress).fitted
    assert progress.seen[0] == 1


@pytest.mark.slow  # two fits of 40 iterations
def test_the_fitted_scene_keeps_only_the_sh_bands_the_schedule_reached(wall_bundle: Path, tmp_path: Path) -> None:
    from panogs_core.gaussians.ply import read_gaussian_ply, write_gaussian_ply
    from panogs_core.io.ply import read_ply_vertices

    short = _fit(wall_bundle, sh_degree=1)  # 40 iterations, the degree rises at 1000: never above 0
    assert short.sh_degree == 0
    path = write_gaussian_ply(
        tmp_path / "g.ply", short, np.zeros_like(short.means), *([np.zeros(len(short.means))] * 2)
    )
    assert not [k for k in read_ply_vertices(path) if k.startswith("f_rest_")]
    assert read_gaussian_ply(path)[0].sh_degree == 0
    reached = _fit(wall_bundle, sh_degree=1, sh_increase_every=20)  # degree 1 from iteration 20 on: trained
    assert reached.sh_degree == 1
    assert np.abs(reached.sh[:, 1:]).max() > 0
