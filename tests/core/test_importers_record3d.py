"""The Record3D importer: the tiny room written as an EXR + JPG export (ARKit quaternion poses in OpenGL axes, K
column-major at a colour size four times the depth's, EXR metres, confidence maps), imported back."""

from __future__ import annotations

import itertools
import json
import shutil
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from capture_room import assert_points_agree, assert_same_cameras, pack_r3d, write_record3d

from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.capture import FrameSelection, MapSources
from panogs_core.io.importers.record3d import Record3DOptions, import_record3d, read_exr_depth

PLACEHOLDER = MapSources(placeholder_maps=True)


@pytest.fixture(scope="module")
def export(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("record3d") / "capture"
    write_record3d(synth_tiny, src)
    return src


class TestImportRecord3D:
    def test_smoke(self, export: Path, synth_tiny: Path, tmp_path: Path) -> None:
        report = import_record3d(export, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        room, scene = open_bundle(synth_tiny), open_bundle(tmp_path / "b")
        assert report.frames_written == len(room.frames)
        pairs = [(f.id, r.id) for f, r in zip(scene.frames, room.frames)]
        assert_same_cameras(scene, room, pairs)  # the depth camera, K scaled down from the colour size
        assert_points_agree(scene, room, pairs)
        assert np.allclose(scene.read_depth(scene.frames[2]), room.read_depth(room.frames[2]), atol=6e-4)
        assert report.gravity_up == (0.0, 1.0, 0.0)
        assert "gravity up in the world: (0, 1, 0)" in report.summary()
        color = cv2.imread(str(tmp_path / "b" / "color" / "000000.jpg"))
        assert color.shape[:2] == (4 * room.camera.height, 4 * room.camera.width)  # copied, the bundle resamples

    def test_low_confidence_depth_is_cleared(self, export: Path, synth_tiny: Path, tmp_path: Path) -> None:
        src = tmp_path / "capture"
        shutil.copytree(export, src)
        conf = cv2.imread(str(src / "conf" / "0.png"), cv2.IMREAD_UNCHANGED)
        conf[:10, :10] = 0
        conf[10:20, :10] = 1
        cv2.imwrite(str(src / "conf" / "0.png"), conf)
        import_record3d(src, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        import_record3d(src, tmp_path / "c", Record3DOptions(maps=PLACEHOLDER, min_confidence=2))
        default, strict = (open_bundle(tmp_path / x) for x in "bc")
        d1, d2 = default.read_depth(default.frames[0]), strict.read_depth(strict.frames[0])
        room = open_bundle(synth_tiny)
        d0 = room.read_depth(room.frames[0])
        assert (d0[:10, :10] > 0).mean() > 0.5, "the test needs depth there"
        assert (d0[10:20, :10] > 0).mean() > 0.5, "the test needs depth there"
        assert np.all(d1[:10, :10] == 0)
        assert np.allclose(d1[10:, :], d0[10:, :], atol=6e-4)
        assert np.all(d2[:20, :10] == 0)
        assert np.allclose(d2[20:, :], d0[20:, :], atol=6e-4)

    def test_motion_rule(self, export: Path, synth_tiny: Path, tmp_path: Path) -> None:
        room = open_bundle(synth_tiny)
        selection = FrameSelection(min_translation=0.3, min_rotation=20.0)
        import_record3d(export, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER, selection=selection))
        kept = [int(f.id) for f in open_bundle(tmp_path / "b").frames]
        assert 1 <= len(kept) < len(room.frames)
        poses = [np.asarray(f.T_world_cam) for f in room.frames]
        for a, b in itertools.pairwise(kept):  # every kept frame moved or turned enough since the one before
            moved = np.linalg.norm(poses[b][:3, 3] - poses[a][:3, 3])
            turned = np.degrees(np.arccos(np.clip((np.trace(poses[a][:3, :3].T @ poses[b][:3, :3]) - 1) / 2, -1, 1)))
            assert moved > 0.3 or turned > 20.0

    def test_truncated_exr_is_named(self, export: Path, tmp_path: Path) -> None:
        src = tmp_path / "capture"
        shutil.copytree(export, src)
        data = (src / "depth" / "3.exr").read_bytes()
        (src / "depth" / "3.exr").write_bytes(data[: len(data) // 2])
        with pytest.raises(InputError, match=r"3\.exr"):
            read_exr_depth(src / "depth" / "3.exr")
        report = import_record3d(src, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        assert "000003" in dict(report.dropped)["depth does not decode"][0]
        assert "3.exr" in report.summary()
        assert "000003" not in [f.id for f in open_bundle(tmp_path / "b").frames]

    def test_exception(self, export: Path, tmp_path: Path) -> None:
        src = tmp_path / "capture"
        shutil.copytree(export, src)
        for exr in (src / "depth").glob("*.exr"):
            if exr.name != "0.exr":
                exr.unlink()
        (src / "depth" / "0.exr").write_bytes((src / "depth" / "0.exr").read_bytes()[:200])
        with pytest.raises(InputError, match=r"0\.exr"):
            import_record3d(src, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        assert not (tmp_path / "b").exists()
        assert not list(tmp_path.glob(".b.partial*"))
        (src / "metadata.json").unlink()
        with pytest.raises(InputError, match=r"metadata\.json is missing"):
            import_record3d(src, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))

    def test_nan_pose_and_missing_colour_are_named(self, export: Path, tmp_path: Path) -> None:
        src = tmp_path / "capture"
        shutil.copytree(export, src)
        meta = json.loads((src / "metadata.json").read_text())
        meta["poses"][1][0] = float("nan")
        meta["poses"][2] = [0.5, 0.5, 0.5, 0.2, 0, 0, 0]  # not a unit quaternion: not a rotation
        (src / "metadata.json").write_text(json.dumps(meta))
        (src / "rgb" / "4.jpg").unlink()
        report = import_record3d(src, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        dropped = dict(report.dropped)
        assert dropped["invalid pose (NaN, infinite or not a rotation)"] == ("000001", "000002")
        assert "4.jpg" in dropped["missing file"][0]
        assert report.frames_written == report.frames_source - 3


class TestImportR3D:
    def test_smoke(self, export: Path, synth_tiny: Path, tmp_path: Path) -> None:
        pytest.importorskip("liblzfse")
        pack_r3d(export, tmp_path / "room.r3d")
        report = import_record3d(tmp_path / "room.r3d", tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        room, scene = open_bundle(synth_tiny), open_bundle(tmp_path / "b")
        assert report.frames_written == len(room.frames)
        assert scene.name == "room (placeholder maps)"
        pairs = [(f.id, r.id) for f, r in zip(scene.frames, room.frames)]
        assert_same_cameras(scene, room, pairs)
        assert_points_agree(scene, room, pairs)

    def test_exception(self, export: Path, tmp_path: Path) -> None:
        pytest.importorskip("liblzfse")
        pack_r3d(export, tmp_path / "room.r3d")
        with zipfile.ZipFile(tmp_path / "room.r3d") as zf, zipfile.ZipFile(tmp_path / "cut.r3d", "w") as out:
            for info in zf.infolist():
                data = zf.read(info)
                out.writestr(info.filename, data[: len(data) // 2] if info.filename == "rgbd/2.depth" else data)
        report = import_record3d(tmp_path / "cut.r3d", tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        assert "2.depth" in dict(report.dropped)["depth does not decode"][0]
        (tmp_path / "bad.r3d").write_bytes(b"PK\x03\x04 not really")
        with pytest.raises(InputError, match=r"bad\.r3d"):
            import_record3d(tmp_path / "bad.r3d", tmp_path / "c", Record3DOptions(maps=PLACEHOLDER))
        assert not (tmp_path / "c").exists()

    def test_a_pruned_export_names_the_poses_left_without_frames(self, export: Path, tmp_path: Path) -> None:
        """A real export whose owner deleted a few frames (rgb and depth) keeps their poses in metadata.json: the
        report names each, instead of counting the capture as shorter than it is."""
        src = tmp_path / "capture"
        shutil.copytree(export, src)
        poses = len(json.loads((src / "metadata.json").read_text())["poses"])
        for path in (src / "rgb" / "3.jpg", src / "depth" / "3.exr", src / "conf" / "3.png"):
            path.unlink(missing_ok=True)
        report = import_record3d(src, tmp_path / "b", Record3DOptions(maps=PLACEHOLDER))
        missing = dict(report.dropped)["missing file"]
        assert len(missing) == 1
        assert missing[0].startswith("000003 (")
        assert missing[0].endswith("has no depth image)")
        assert report.frames_source == poses
        assert report.frames_written == poses - 1
