"""The TUM RGB-D importer: the tiny room written as a TUM sequence (depth / 5000, streams off in time, ground truth
rows between frames), imported back: poses, intrinsics, points, drops by reason, and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from capture_room import assert_points_agree, assert_same_cameras, export_maps, write_tum

from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.capture import FrameSelection, MapSources
from panogs_core.io.importers.tum import FREIBURG_CAMERAS, TumOptions, associate, import_tum


def _intrinsics(room: Path, path: Path) -> Path:
    cam = open_bundle(room).camera
    path.write_text(f"{cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n")
    return path


@pytest.fixture(scope="module")
def sequence(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("tum") / "rgbd_dataset_synthetic"
    write_tum(synth_tiny, src)
    _intrinsics(synth_tiny, src / "intrinsics.txt")
    return src


def _options(src: Path, **kw: object) -> TumOptions:
    base: dict[str, object] = {"intrinsics": src / "intrinsics.txt", "maps": MapSources(placeholder_maps=True)}
    return TumOptions(**{**base, **kw})  # type: ignore[arg-type]


class TestImportTum:
    def test_smoke(self, sequence: Path, synth_tiny: Path, tmp_path: Path) -> None:
        report = import_tum(sequence, tmp_path / "b", _options(sequence))
        room = open_bundle(synth_tiny)
        scene = open_bundle(tmp_path / "b")
        assert report.frames_written == len(room.frames) == len(scene.frames)
        assert scene.depth_scale == 5000.0
        pairs = [(f.id, r.id) for f, r in zip(scene.frames, room.frames)]
        assert_same_cameras(scene, room, pairs)
        assert_points_agree(scene, room, pairs)
        assert np.array_equal(scene.read_depth(scene.frames[3]), room.read_depth(room.frames[3]))
        assert report.depth_range is not None
        assert 0 < report.depth_range[0] <= report.depth_range[2]
        assert "panogs run" in report.summary()

    def test_frames_without_a_pose_in_tolerance_are_dropped_and_counted(self, sequence: Path, tmp_path: Path) -> None:
        src = tmp_path / "seq"
        shutil.copytree(sequence, src)
        lines = (src / "groundtruth.txt").read_text().splitlines()
        (src / "groundtruth.txt").write_text("\n".join(lines[:1] + lines[3:]) + "\n")  # frame 0's row gone
        report = import_tum(src, tmp_path / "b", _options(src))
        assert report.frames_written == len(lines[1:]) // 2 - 1
        reasons = dict(report.dropped)
        assert list(reasons["no pose within 0.02 s"]) == ["000000 (depth 1305031102.000000)"]
        assert "no pose within 0.02 s" in report.summary()

    def test_nan_pose_is_named_and_the_rest_written(self, sequence: Path, tmp_path: Path) -> None:
        src = tmp_path / "seq"
        shutil.copytree(sequence, src)
        lines = (src / "groundtruth.txt").read_text().splitlines()
        stamp = lines[3].split()[0]
        lines[3] = f"{stamp} nan 0 0 0 0 0 1"
        (src / "groundtruth.txt").write_text("\n".join(lines) + "\n")
        report = import_tum(src, tmp_path / "b", _options(src))
        invalid = dict(report.dropped)["invalid pose (NaN, infinite or not a rotation)"]
        assert invalid == ("000001",)
        assert "000001" not in [f.id for f in open_bundle(tmp_path / "b").frames]

    def test_selection(self, sequence: Path, tmp_path: Path) -> None:
        report = import_tum(
            sequence, tmp_path / "b", _options(sequence, selection=FrameSelection(stride=2, max_frames=3))
        )
        assert [f.id for f in open_bundle(tmp_path / "b").frames] == ["000000", "000004", "000010"]
        assert report.not_selected == report.frames_source - 3

    def test_maps_from_folders(self, sequence: Path, synth_tiny: Path, tmp_path: Path) -> None:
        stamps = sorted(p.stem for p in (sequence / "depth").glob("*.png"))
        features, masks = export_maps(open_bundle(synth_tiny), stamps, tmp_path / "maps")
        maps = MapSources(features=features, masks=masks, feature_space="minilm-l6")
        import_tum(sequence, tmp_path / "b", _options(sequence, maps=maps))
        scene = open_bundle(tmp_path / "b")
        room = open_bundle(synth_tiny)
        assert len(scene.feature_frames) == len(room.feature_frames)
        assert np.array_equal(scene.read_masks(scene.frames[2]), room.read_masks(room.frames[2]))

    def test_freiburg_camera(self, sequence: Path, tmp_path: Path) -> None:
        import_tum(sequence, tmp_path / "b", _options(sequence, intrinsics=None, camera="freiburg3"))
        cam = open_bundle(tmp_path / "b").camera
        fx, _, cx, _ = FREIBURG_CAMERAS["freiburg3"]
        assert (cam.width, cam.height) == (160, 120)  # the published 640x480 values scaled to the depth size
        assert np.isclose(cam.fx, fx / 4)
        assert np.isclose(cam.cx, (cx + 0.5) / 4 - 0.5)

    def test_without_maps_writes_a_bundle_whose_maps_the_run_computes(self, sequence: Path, tmp_path: Path) -> None:
        report = import_tum(sequence, tmp_path / "b", _options(sequence, maps=MapSources()))
        assert report.maps_to_compute == ("masks", "features")
        assert not report.placeholder_maps
        assert "--masks-model" in report.summary()
        assert "--features-model" in report.summary()
        bundle = open_bundle(tmp_path / "b")
        assert bundle.feature_dim == 0
        assert bundle.feature_space == ""
        assert not bundle.feature_frames
        assert not bundle.mask_frames
        assert all(f.color is not None for f in bundle.frames)
        assert "features" not in json.loads((tmp_path / "b" / "scene.json").read_text())

    def test_exception(self, sequence: Path, tmp_path: Path) -> None:
        with pytest.raises(InputError, match="--camera freiburg1"):
            import_tum(sequence, tmp_path / "a", TumOptions(maps=MapSources(placeholder_maps=True)))
        src = tmp_path / "seq"
        shutil.copytree(sequence, src)
        lines = (src / "rgb.txt").read_text().splitlines()
        shifted = [
            line if line.startswith("#") else f"{float(line.split()[0]) + 0.5:.6f} {line.split()[1]}" for line in lines
        ]
        (src / "rgb.txt").write_text("\n".join(shifted) + "\n")
        with pytest.raises(InputError, match=r"depth\.txt.*0\.02 s"):
            import_tum(src, tmp_path / "a", _options(src))
        assert not (tmp_path / "a").exists()
        assert not list(tmp_path.glob(".a.partial*"))

    def test_unreadable_depth_is_named_and_nothing_half_written(self, sequence: Path, tmp_path: Path) -> None:
        src = tmp_path / "seq"
        shutil.copytree(sequence, src)
        for png in (src / "depth").glob("*.png"):
            png.write_bytes(png.read_bytes()[:40])  # truncated
        with pytest.raises(InputError, match=r"1305031102\.000000\.png"):
            import_tum(src, tmp_path / "b", _options(src))
        assert not (tmp_path / "b").exists()
        assert not list(tmp_path.glob(".b.partial*"))


def test_associate_takes_the_nearest_within_tolerance() -> None:
    query = np.array([0.0, 1.0, 2.0, 3.0])
    reference = np.array([2.015, 0.01, 0.99, 1.02, 5.0])
    assert associate(query, reference, 0.02).tolist() == [1, 2, 0, -1]
    assert associate(query, np.array([]), 0.02).tolist() == [-1, -1, -1, -1]


def test_features_without_masks_leave_the_masks_to_the_run(sequence: Path, synth_tiny: Path, tmp_path: Path) -> None:
    stamps = sorted(p.stem for p in (sequence / "depth").glob("*.png"))
    features, _ = export_maps(open_bundle(synth_tiny), stamps, tmp_path / "maps")
    report = import_tum(sequence, tmp_path / "b", _options(sequence, maps=MapSources(features=features)))
    assert report.maps_to_compute == ("masks",)
    assert "--masks-model" in report.summary()
    assert "--features-model" not in report.summary()
    scene = open_bundle(tmp_path / "b")
    assert scene.feature_frames
    assert not scene.mask_frames
