"""Stage 2, visibility: projection, pixel rounding, bounds, depth test, CSR output (known answers)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from panogs_core.errors import ConfigError, ShapeError
from panogs_core.stages.visibility import Visibility, VisibilityConfig, compute_visibility, frame_visibility
from panogs_core.types import Camera, Frame

# 8 x 6 image; every quantity below is exact in float32 (powers of two and halves).
CAM = Camera(width=8, height=6, fx=4.0, fy=4.0, cx=3.5, cy=2.5)


@dataclass
class FakeScene:
    """The part of ``bundle.Scene`` that visibility reads."""

    camera: Camera
    frames: tuple[Frame, ...]
    depths: dict[str, np.ndarray] = field(default_factory=dict)

    def read_depth(self, frame: Frame) -> np.ndarray:
        return self.depths[frame.id]


def _frame(fid: str, pose: np.ndarray | None = None, *, features: bool = True, masks: bool = False) -> Frame:
    return Frame(
        id=fid,
        T_world_cam=np.eye(4) if pose is None else pose,
        depth=f"depth/{fid}.png",
        features=f"features/{fid}.npy" if features else None,
        masks=f"masks/{fid}.png" if masks else None,
    )


def _plane_scene(depth_value: float = 2.0) -> FakeScene:
    """Identity camera (at the origin, looking down +z) facing the plane z = depth_value."""
    frame = _frame("0")
    depth = np.full((CAM.height, CAM.width), depth_value, dtype=np.float32)
    return FakeScene(camera=CAM, frames=(frame,), depths={"0": depth})


def _expected_plane_pixels(points: np.ndarray) -> dict[int, tuple[int, int]]:
    """Float64 oracle: in front and rint inside the image (on-plane points pass the depth test)."""
    out = {}
    for i, (x, y, z) in enumerate(points.astype(np.float64)):
        if z <= 0:
            continue
        u, v = np.rint(CAM.fx * x / z + CAM.cx), np.rint(CAM.fy * y / z + CAM.cy)
        if 0 <= u <= CAM.width - 1 and 0 <= v <= CAM.height - 1:
            out[i] = (int(v), int(u))
    return out


class TestComputeVisibility:
    def test_smoke(self) -> None:
        scene = _plane_scene()
        vis = compute_visibility(scene, np.array([[0.0, 0.0, 2.0]], np.float32), VisibilityConfig())
        assert vis.frame_ids == ("0",)
        assert vis.frame(0)[0].tolist() == [0]

    def test_plane_frustum_exact(self) -> None:
        # A grid on the plane z = 2, much wider than the frustum: exactly the oracle's points are seen.
        xs, ys = np.meshgrid(np.linspace(-6, 6, 61), np.linspace(-5, 5, 47))
        points = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)], 1).astype(np.float32)
        vis = compute_visibility(_plane_scene(), points, VisibilityConfig())
        idx, row, col = vis.frame(0)
        expected = _expected_plane_pixels(points)
        assert 0 < len(expected) < len(points)
        assert idx.tolist() == sorted(expected)
        assert list(zip(row.tolist(), col.tolist(), strict=True)) == [expected[i] for i in sorted(expected)]

    def test_occluded_point_not_seen(self) -> None:
        points = np.array(
            [
                [0.0, 0.0, 2.0],  # on the wall: seen
                [0.0, 0.0, 3.0],  # behind the wall, same pixel: occluded
                [0.0, 0.0, 2.0 * 1.06],  # 6% behind: inside rtol 0.07
                [0.0, 0.0, 2.0 * 1.08],  # 8% behind: outside
                [0.0, 0.0, 2.0 * 0.94],  # 6% in front
                [0.0, 0.0, 1.0],  # floating in front of the wall (the sensor would see it; here it is not)
            ],
            np.float32,
        )
        vis = compute_visibility(_plane_scene(), points, VisibilityConfig())
        assert vis.frame(0)[0].tolist() == [0, 2, 4]

    def test_behind_camera_never_seen(self) -> None:
        # Mirror images of visible points behind the camera would project inside the image if z were not
        # guarded (x/z flips sign twice); make the depth agree with |z| too so only the z guard stops them.
        points = np.array([[0, 0, -2.0], [0.5, 0.5, -2.0], [-0.5, 0.25, -2.0], [0, 0, 0]], np.float32)
        vis = compute_visibility(_plane_scene(), points, VisibilityConfig())
        assert vis.frame(0)[0].size == 0
        # Same with a camera turned around: points in front of it are seen, the ones behind are not.
        turn = np.diag([-1.0, 1.0, -1.0, 1.0])  # 180 degrees about y: looks down -z
        scene = _plane_scene()
        scene.frames = (_frame("0", turn),)
        vis = compute_visibility(scene, np.vstack([points, -points[:3]]), VisibilityConfig())
        assert vis.frame(0)[0].tolist() == [0, 1, 2]

    def test_pixel_rounding_half_to_even_and_bounds(self) -> None:
        # u = 4 x / 2 + 3.5 = 2 x + 3.5 at z = 2: x chosen so u lands exactly on halves.
        us = np.array([2.5, 3.5, -0.5, 6.5, 7.5, -0.51])
        points = np.stack([(us - 3.5) / 2.0, np.zeros_like(us), np.full_like(us, 2.0)], 1).astype(np.float32)
        vis = compute_visibility(_plane_scene(), points, VisibilityConfig())
        idx, row, col = vis.frame(0)
        # 2.5 -> 2, 3.5 -> 4 (half to even), -0.5 -> -0 (in), 6.5 -> 6, 7.5 -> 8 (out), -0.51 -> -1 (out)
        assert idx.tolist() == [0, 1, 2, 3]
        assert col.tolist() == [2, 4, 0, 6]
        assert row.tolist() == [2, 2, 2, 2]  # v = 2.5 -> 2

    def test_no_depth_means_unseen(self) -> None:
        scene = _plane_scene()
        scene.depths["0"][2, 4] = 0.0  # a hole where the point at the image centre lands
        vis = compute_visibility(scene, np.array([[0.0, 0.0, 2.0], [-0.5, 0.0, 2.0]], np.float32),
                                 VisibilityConfig(depth_atol=0.5))  # fmt: skip
        assert vis.frame(0)[0].tolist() == [1]

    def test_depth_atol(self) -> None:
        points = np.array([[0.0, 0.0, 2.3]], np.float32)  # 15% behind the wall
        assert compute_visibility(_plane_scene(), points, VisibilityConfig()).frame(0)[0].size == 0
        seen = compute_visibility(_plane_scene(), points, VisibilityConfig(depth_atol=0.2, depth_max_tol=None))
        assert seen.frame(0)[0].tolist() == [0]
        capped = compute_visibility(_plane_scene(), points, VisibilityConfig(depth_atol=0.2))  # 0.15 m at most
        assert capped.frame(0)[0].size == 0

    def test_depth_max_tol_caps_the_tolerance(self) -> None:
        # The plane stands at 2 m: 7 % is 0.14 m. A point 0.1 m behind it passes, unless the cap is under 0.1 m.
        points = np.array([[0.0, 0.0, 2.1]], np.float32)
        assert compute_visibility(_plane_scene(), points, VisibilityConfig()).frame(0)[0].tolist() == [0]
        capped = VisibilityConfig(depth_max_tol=0.05)
        assert compute_visibility(_plane_scene(), points, capped).frame(0)[0].size == 0
        near = np.array([[0.0, 0.0, 2.04]], np.float32)  # within the cap: still seen
        assert compute_visibility(_plane_scene(), near, capped).frame(0)[0].tolist() == [0]

    def test_non_finite_pose_sees_nothing(self) -> None:
        bad = np.eye(4)
        bad[0, 3] = -np.inf
        scene = _plane_scene()
        scene.frames = (_frame("0", bad), _frame("1"))
        scene.depths["1"] = scene.depths["0"]
        vis = compute_visibility(scene, np.array([[0.0, 0.0, 2.0]], np.float32), VisibilityConfig())
        assert vis.frame_ids == ("0", "1")
        assert vis.offsets.tolist() == [0, 0, 1]

    def test_pose_is_camera_to_world(self) -> None:
        # Camera moved to x = 1: the wall point at x = 1 is at the image centre (u = 3.5 -> 4, v = 2.5 -> 2).
        pose = np.eye(4)
        pose[0, 3] = 1.0
        scene = _plane_scene()
        scene.frames = (_frame("0", pose),)
        idx, row, col = compute_visibility(scene, np.array([[1.0, 0.0, 2.0]], np.float32), VisibilityConfig()).frame(0)
        assert (idx.tolist(), row.tolist(), col.tolist()) == ([0], [2], [4])

    def test_default_frames_and_order(self) -> None:
        depth = np.full((CAM.height, CAM.width), 2.0, np.float32)
        frames = (
            _frame("a", features=False, masks=False),  # geometry only: not a key frame
            _frame("b", features=False, masks=True),
            _frame("c", features=True, masks=False),
        )
        scene = FakeScene(camera=CAM, frames=frames, depths=dict.fromkeys("abc", depth))
        points = np.array([[0.0, 0.0, 2.0], [9.0, 9.0, 2.0]], np.float32)
        vis = compute_visibility(scene, points, VisibilityConfig())
        assert vis.frame_ids == ("b", "c")
        only_a = compute_visibility(scene, points, VisibilityConfig(), frames=frames[:1])
        assert only_a.frame_ids == ("a",)

    def test_progress_per_frame(self) -> None:
        scene = _plane_scene()
        scene.frames = (_frame("0"), _frame("1"))
        scene.depths["1"] = scene.depths["0"]
        calls: list[tuple[int, int]] = []
        compute_visibility(scene, np.zeros((3, 3), np.float32), VisibilityConfig(),
                           on_progress=lambda d, t: calls.append((d, t)))  # fmt: skip
        assert calls == [(1, 2), (2, 2)]

    def test_cardinality_and_dtypes(self) -> None:
        rng = np.random.default_rng(0)
        points = (rng.uniform(-3, 3, (500, 3)) + np.array([0, 0, 2])).astype(np.float32)
        vis = compute_visibility(_plane_scene(), points, VisibilityConfig(depth_rtol=0.5))
        assert vis.offsets.dtype == np.int64
        assert vis.offsets.shape == (2,)
        for arr in (vis.point_index, vis.pixel_row, vis.pixel_col):
            assert arr.dtype == np.int32
            assert arr.shape == (vis.offsets[-1],)
        assert np.all(np.diff(vis.point_index) > 0)  # ascending, each point once per frame

    def test_exception(self) -> None:
        with pytest.raises(ShapeError, match="points"):
            compute_visibility(_plane_scene(), np.zeros((4, 2), np.float32), VisibilityConfig())
        scene = _plane_scene()
        scene.depths["0"] = np.ones((3, 3), np.float32)
        with pytest.raises(ShapeError, match="depth"):
            compute_visibility(scene, np.zeros((4, 3), np.float32), VisibilityConfig())

    def test_frame_visibility_matches_oracle_random(self) -> None:
        # Random points and pose against a float64 oracle; the depth test is made to pass for z > 0.1 m.
        rng = np.random.default_rng(1)
        points = rng.uniform(-2, 2, (2000, 3)).astype(np.float32)
        angle = 0.3
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        pose[:3, 3] = [0.1, -0.2, -3.0]
        T_cam_world = np.linalg.inv(pose)
        cam_pts = points.astype(np.float64) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        far_wall = np.full((CAM.height, CAM.width), 100.0, np.float32)  # tolerance 99.9 m: all in front pass
        cfg = VisibilityConfig(depth_rtol=0.999, depth_max_tol=None)
        idx, row, col, _ = frame_visibility(points, T_cam_world, CAM, far_wall, cfg)
        u = np.rint(CAM.fx * cam_pts[:, 0] / cam_pts[:, 2] + CAM.cx)
        v = np.rint(CAM.fy * cam_pts[:, 1] / cam_pts[:, 2] + CAM.cy)
        oracle = (cam_pts[:, 2] > 0.1) & (u >= 0) & (u <= CAM.width - 1) & (v >= 0) & (v <= CAM.height - 1)
        assert idx.tolist() == np.flatnonzero(oracle).tolist()
        assert col.tolist() == u[oracle].astype(int).tolist()
        assert row.tolist() == v[oracle].astype(int).tolist()


class TestVisibilityData:
    def test_save_load_round_trip(self, tmp_path: Path) -> None:
        vis = Visibility(
            frame_ids=("000", "frame_7"),
            offsets=np.array([0, 2, 3], np.int64),
            point_index=np.array([1, 4, 0], np.int32),
            pixel_row=np.array([0, 1, 2], np.int32),
            pixel_col=np.array([3, 4, 5], np.int32),
        )
        path = tmp_path / "vis.tmp"  # no .npz suffix: saved at exactly this path
        vis.save(path)
        back = Visibility.load(path)
        assert back.frame_ids == vis.frame_ids
        assert back.num_frames == 2
        for name in ("offsets", "point_index", "pixel_row", "pixel_col"):
            assert np.array_equal(getattr(back, name), getattr(vis, name))
        assert back.frame(1)[0].tolist() == [0]

    def test_empty_round_trip(self, tmp_path: Path) -> None:
        empty = np.zeros(0, np.int32)
        vis = Visibility(frame_ids=(), offsets=np.zeros(1, np.int64), point_index=empty, pixel_row=empty,
                         pixel_col=empty)  # fmt: skip
        vis.save(tmp_path / "v.npz")
        assert Visibility.load(tmp_path / "v.npz").num_frames == 0

    def test_exception(self) -> None:
        with pytest.raises(ShapeError, match="offsets"):
            Visibility(frame_ids=("a",), offsets=np.zeros(1, np.int64), point_index=np.zeros(0, np.int32),
                       pixel_row=np.zeros(0, np.int32), pixel_col=np.zeros(0, np.int32))  # fmt: skip


class TestVisibilityConfig:
    @pytest.mark.parametrize(
        ("name", "value"),
        [("depth_rtol", 0.0), ("depth_rtol", 1.5), ("depth_rtol", float("nan")), ("depth_atol", -0.1),
         ("depth_max_tol", 0.0), ("depth_max_tol", float("inf")), ("z_near", 0.0)],
    )  # fmt: skip
    def test_exception(self, name: str, value: float) -> None:
        with pytest.raises(ConfigError, match=f"visibility.{name}"):
            VisibilityConfig(**{name: value})

    def test_defaults_match_reference(self) -> None:
        cfg = VisibilityConfig()
        assert cfg.depth_rtol == 0.07
        assert cfg.depth_atol == 0.0
        assert cfg.depth_max_tol == 0.15  # ours (docs/method.md §3.1): the reference has no cap


class TestDepthResidual:
    def test_residual_of_each_seen_pair(self, tmp_path: Path) -> None:
        # Plane at 2 m; points at 2.0, 2.05 and 1.9 m depth on the optical axis region: residual (z - D) / D.
        scene = _plane_scene(2.0)
        points = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.05], [-0.5, 0.0, 1.9], [0.0, 0.5, 2.5]], np.float32)
        vis = compute_visibility(scene, points, VisibilityConfig())  # type: ignore[arg-type]
        np.testing.assert_array_equal(vis.point_index, [0, 1, 2])  # 2.5 m is 25 % off: not seen
        assert vis.depth_residual is not None
        np.testing.assert_allclose(vis.depth_residual.astype(np.float64), [0.0, 0.025, -0.05], atol=1e-3)
        vis.save(tmp_path / "vis.npz")
        back = Visibility.load(tmp_path / "vis.npz")
        np.testing.assert_array_equal(back.depth_residual, vis.depth_residual)

    def test_checkpoints_without_residual_still_load(self, tmp_path: Path) -> None:
        empty = np.zeros(0, np.int32)
        old = Visibility(frame_ids=(), offsets=np.zeros(1, np.int64), point_index=empty, pixel_row=empty,
                         pixel_col=empty)  # fmt: skip
        old.save(tmp_path / "old.npz")
        assert Visibility.load(tmp_path / "old.npz").depth_residual is None

    def test_residual_shape_checked(self) -> None:
        with pytest.raises(ShapeError, match="depth_residual"):
            Visibility(frame_ids=("a",), offsets=np.array([0, 2]), point_index=np.zeros(2, np.int32),
                       pixel_row=np.zeros(2, np.int32), pixel_col=np.zeros(2, np.int32),
                       depth_residual=np.zeros(3, np.float16))  # fmt: skip
