"""ScanNet and Replica importers: small layouts written in tmp_path, imported, then validated."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.common import masks_to_ids, resample_nearest
from panogs_core.io.importers.replica import import_replica
from panogs_core.io.importers.scannet import import_scannet
from panogs_core.io.ply import write_ply
from panogs_core.types import Camera, Vocabulary

D = 6


def _pose(i: int) -> np.ndarray:  # (4, 4) rigid
    a = 0.2 * i
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    pose[:3, 3] = [0.1 * i, 0.0, 1.0]
    return pose


def _depth(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    return rng.integers(0, 5000, (h, w)).astype(np.uint16)


def _scannet(root: Path, n: int = 12, bad_pose: int = 3) -> Path:
    """n frames, 32x24 depth, 40x30 colour; features on even frames, masks on frames divisible by 3."""
    rng = np.random.default_rng(1)
    for sub in ("color", "depth", "pose", "intrinsic", "features", "masks"):
        (root / sub).mkdir(parents=True)
    K = np.array([[28.0, 0, 15.5, 0], [0, 29.0, 11.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", K)
    for i in range(n):
        assert cv2.imwrite(str(root / "depth" / f"{i}.png"), _depth(rng, 24, 32))
        assert cv2.imwrite(str(root / "color" / f"{i}.jpg"), rng.integers(0, 255, (30, 40, 3), dtype=np.uint8))
        pose = np.full((4, 4), -np.inf) if i == bad_pose else _pose(i)
        np.savetxt(root / "pose" / f"{i}.txt", pose)
        if i % 2 == 0:
            np.save(root / "features" / f"{i}.npy", rng.normal(size=(4, 5, D)).astype(np.float16))
        if i % 3 == 0:
            assert cv2.imwrite(str(root / "masks" / f"{i}.png"), rng.integers(0, 9, (24, 32), dtype=np.uint8))
    return root


def _replica(root: Path, n: int = 5, depth_hw: tuple[int, int] = (34, 60)) -> Path:
    """NICE-SLAM layout, depth at 1/20 of 1200x680; frame 2 has a NaN pose, frame 4 colour masks + f64 map."""
    rng = np.random.default_rng(2)
    for sub in ("results", "features", "masks"):
        (root / sub).mkdir(parents=True)
    lines = []
    for i in range(n):
        digits = f"{i:06d}"
        assert cv2.imwrite(str(root / "results" / f"depth{digits}.png"), _depth(rng, *depth_hw))
        assert cv2.imwrite(str(root / "results" / f"frame{digits}.jpg"), np.full((68, 120, 3), 90, np.uint8))
        pose = np.full((4, 4), np.nan) if i == 2 else _pose(i)
        lines.append(" ".join(f"{v:.8f}" for v in pose.reshape(-1)))
        features = rng.normal(size=(3, 4, D))
        if i == 4:
            np.save(root / "features" / f"{digits}.npy", features)  # float64, plain stem: converted
            colours = np.zeros((17, 30, 3), np.uint8)
            colours[:8, :, 2] = 255
            colours[8:, :10] = (0, 255, 0)
            assert cv2.imwrite(str(root / "masks" / f"frame{digits}.png"), colours)
        elif i != 1:
            np.save(root / "features" / f"frame{digits}.npy", features.astype(np.float32))
            masks = rng.integers(0, 5, (17, 30)).astype(np.uint16)
            assert cv2.imwrite(str(root / "masks" / f"frame{digits}.png"), masks)
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    return root


class TestImportScannet:
    def test_smoke(self, tmp_path: Path) -> None:
        src = _scannet(tmp_path / "scene0000_00")
        report = import_scannet(src, tmp_path / "bundle")
        assert report.frames_written == 11
        assert report.frames_skipped_invalid_pose == ("000003",)
        assert report.frames_without_features == 5  # odd ids 1, 5, 7, 9, 11 (3 was skipped)
        assert report.frames_without_masks == 8  # masks on 0, 3, 6, 9, but 3 was skipped
        assert "skipped 1 frames with invalid poses: 000003" in report.summary()
        scene = open_bundle(report.bundle)
        assert scene.name == "scene0000_00"
        assert scene.camera == Camera(width=32, height=24, fx=28.0, fy=29.0, cx=15.5, cy=11.5)
        assert scene.feature_dim == D
        assert scene.feature_space == "clip-vit-b32"
        ids = [f.id for f in scene.frames]
        assert ids == [f"{i:06d}" for i in range(12) if i != 3]  # integer order: 2 before 10
        assert [f.id for f in scene.mask_frames] == ["000000", "000006", "000009"]
        np.testing.assert_allclose(scene.frames[-1].T_world_cam, _pose(11))

    def test_depth_copied_exactly(self, tmp_path: Path) -> None:
        src = _scannet(tmp_path / "s")
        scene = open_bundle(import_scannet(src, tmp_path / "b").bundle)
        raw = cv2.imread(str(src / "depth" / "10.png"), cv2.IMREAD_UNCHANGED)
        frame = next(f for f in scene.frames if f.id == "000010")
        np.testing.assert_array_equal(np.round(scene.read_depth(frame) * 1000.0), raw)
        color = scene.read_color(frame)
        assert color is not None
        assert color.shape == (24, 32, 3)

    def test_stride_geometry_vocabulary(self, tmp_path: Path) -> None:
        src = _scannet(tmp_path / "s")
        pts = np.random.default_rng(0).normal(size=(7, 3)).astype(np.float32)
        write_ply(
            tmp_path / "mesh.ply",
            {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]},
            faces=np.array([[0, 1, 2]]),
        )
        vocab = Vocabulary(("wall", "chair"), ("stuff", "thing"), np.eye(2, D, dtype=np.float32))
        report = import_scannet(
            src,
            tmp_path / "b",
            stride=4,
            geometry=tmp_path / "mesh.ply",
            vocabulary=vocab,
            name="x",
            feature_space="s",
        )
        assert report.frames_written == 3  # 0, 4, 8
        scene = open_bundle(report.bundle)
        assert [f.id for f in scene.frames] == ["000000", "000004", "000008"]
        # the frames the stride left out keep their pose (frame 3's -inf pose is not one), as the capture importers'
        left_out = [fid for fid, _ in scene.skipped_poses]
        assert left_out == [f"{i:06d}" for i in (1, 2, 5, 6, 7, 9, 10, 11)]
        np.testing.assert_allclose(dict(scene.skipped_poses)["000005"], _pose(5), atol=1e-12)
        assert scene.up is None  # the export does not say where gravity is: the pipeline estimates it
        geometry = scene.read_geometry()
        assert geometry is not None
        np.testing.assert_array_equal(geometry.points, pts)
        assert scene.vocabulary is not None
        assert scene.vocabulary.names == ("wall", "chair")
        assert (scene.name, scene.feature_space) == ("x", "s")

    def test_exception(self, tmp_path: Path) -> None:
        src = _scannet(tmp_path / "s")
        with pytest.raises(InputError, match="not an empty folder"):
            import_scannet(src, src)
        with pytest.raises(InputError, match="stride"):
            import_scannet(src, tmp_path / "b", stride=0)
        for path in (src / "features").iterdir():
            path.unlink()
        with pytest.raises(InputError, match="no feature maps"):
            import_scannet(src, tmp_path / "b3")
        (src / "intrinsic" / "intrinsic_depth.txt").unlink()
        with pytest.raises(InputError, match=r"intrinsic_depth\.txt"):
            import_scannet(src, tmp_path / "b4")


class TestImportReplica:
    def test_smoke_default_camera_scaled_to_depth(self, tmp_path: Path) -> None:
        report = import_replica(_replica(tmp_path / "room0"), tmp_path / "b")
        assert report.frames_written == 4
        assert report.frames_skipped_invalid_pose == ("000002",)
        assert report.frames_without_features == 1
        assert report.frames_without_masks == 1
        scene = open_bundle(report.bundle)
        assert scene.depth_scale == 6553.5
        cam = scene.camera
        assert (cam.width, cam.height) == (60, 34)
        assert cam.fx == pytest.approx(30.0)
        assert cam.cx == pytest.approx((599.5 + 0.5) * 60 / 1200 - 0.5)
        assert [f.id for f in scene.frames] == ["000000", "000001", "000003", "000004"]
        colour_masks = scene.read_masks(scene.frames[-1])
        assert sorted(np.unique(colour_masks).tolist()) == [0, 1, 2]  # black, blue, green
        features = scene.read_features(scene.frames[-1])
        assert features.dtype == np.float32
        assert features.shape == (3, 4, D)

    def test_cam_params_and_explicit_camera(self, tmp_path: Path) -> None:
        src = _replica(tmp_path / "office0")
        params = {"camera": {"w": 60, "h": 34, "fx": 31.0, "fy": 32.0, "cx": 29.0, "cy": 16.0, "scale": 5000.0}}
        (tmp_path / "cam_params.json").write_text(json.dumps(params))  # one folder up, as in NICE-SLAM
        scene = open_bundle(import_replica(src, tmp_path / "b1").bundle)
        assert scene.camera == Camera(60, 34, 31.0, 32.0, 29.0, 16.0)
        assert scene.depth_scale == 5000.0
        half = Camera(width=30, height=17, fx=15.0, fy=15.0, cx=14.5, cy=8.0)
        scene = open_bundle(import_replica(src, tmp_path / "b2", camera=half, depth_scale=6553.5).bundle)
        assert scene.camera == half
        raw = cv2.imread(str(src / "results" / "depth000000.png"), cv2.IMREAD_UNCHANGED)
        depth = scene.read_depth(scene.frames[0])
        assert depth.shape == (17, 30)
        np.testing.assert_array_equal(np.round(depth * 6553.5), raw[1::2, 1::2])  # centres of 2x2 blocks

    def test_resize(self, tmp_path: Path) -> None:
        report = import_replica(_replica(tmp_path / "r"), tmp_path / "b", resize=(20, 10), stride=3)
        scene = open_bundle(report.bundle)
        assert (scene.camera.width, scene.camera.height) == (20, 10)
        assert scene.camera.fx == pytest.approx(600.0 * 20 / 1200)
        assert [f.id for f in scene.frames] == ["000000", "000003"]
        # left out by the stride: 1 and 4 by their pose; 2 has a NaN pose and is not recorded
        assert [fid for fid, _ in scene.skipped_poses] == ["000001", "000004"]
        np.testing.assert_allclose(dict(scene.skipped_poses)["000004"], _pose(4), atol=1e-7)

    def test_exception(self, tmp_path: Path) -> None:
        src = _replica(tmp_path / "r")
        (src / "traj.txt").unlink()
        with pytest.raises(InputError, match=r"traj\.txt"):
            import_replica(src, tmp_path / "b")
        with pytest.raises(InputError, match="depthXXXXXX"):
            import_replica(tmp_path / "nothing", tmp_path / "b")


class TestHelpers:
    def test_resample_nearest_uses_pixel_centres(self) -> None:
        image = np.arange(16).reshape(4, 4)
        np.testing.assert_array_equal(resample_nearest(image, (2, 2)), [[5, 7], [13, 15]])
        np.testing.assert_array_equal(resample_nearest(image, (4, 4)), image)
        np.testing.assert_array_equal(resample_nearest(np.array([[1, 2]]), (1, 4)), [[1, 1, 2, 2]])

    def test_scale_camera_keeps_rays(self) -> None:
        cam = Camera(1200, 680, 600.0, 600.0, 599.5, 339.5)
        small = cam.scaled(600, 340)
        # Output pixel (u, v) covers input pixels 2u, 2u+1: its ray is the mean of theirs.
        u = 10
        ray_small = (u - small.cx) / small.fx
        ray_big = ((2 * u + 0.5) - cam.cx) / cam.fx
        assert ray_small == pytest.approx(ray_big)

    def test_masks_to_ids(self) -> None:
        grey = np.array([[0, 3], [3, 7]], np.uint8)
        np.testing.assert_array_equal(masks_to_ids(grey), grey)
        colour = np.zeros((2, 2, 3), np.uint8)
        colour[0, 0] = (10, 20, 30)
        colour[1, 1] = (1, 2, 3)
        ids = masks_to_ids(colour)
        assert ids[0, 1] == ids[1, 0] == 0
        assert {ids[0, 0], ids[1, 1]} == {1, 2}
