"""The 7-Scenes importer: its layout, invalid depth, stride, optional and placeholder maps, and the CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.sevenscenes import import_sevenscenes
from panogs_core.pipeline.run import resolve_scene_vocabulary
from panogs_core.types import Vocabulary

ROOT = Path(__file__).resolve().parents[2]
W, H = 16, 12


def _sequence(root: Path, frames: int = 4) -> Path:
    root.mkdir(parents=True)
    np.savetxt(root / "camera-intrinsics.txt", [[14.6, 0, 8], [0, 14.6, 6], [0, 0, 1]])
    for i in range(frames):
        depth = np.full((H, W), 1500, np.uint16)
        depth[0, 0] = 65535  # no measurement
        depth[0, 1] = 0
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), depth)
        cv2.imwrite(str(root / f"frame-{i:06d}.color.jpg"), np.full((H, W, 3), 40 * i, np.uint8))
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        np.savetxt(root / f"frame-{i:06d}.pose.txt", pose)
    return root


def test_a_sequence_imports_with_placeholder_maps(tmp_path: Path) -> None:
    src = _sequence(tmp_path / "seq")
    report = import_sevenscenes(src, tmp_path / "b", stride=2, placeholder_maps=True)
    assert report.frames_written == 2
    scene = open_bundle(tmp_path / "b")
    assert "placeholder maps" in scene.name
    assert [f.id for f in scene.frames] == ["000000", "000002"]
    assert (scene.camera.width, scene.camera.height, scene.camera.fx) == (W, H, 14.6)
    assert len(scene.feature_frames) == len(scene.mask_frames) == 1
    depth = scene.read_depth(scene.frames[1])
    assert depth[0, 0] == 0  # 65535 means no depth
    assert depth[0, 1] == 0
    assert np.allclose(depth[1:], 1.5)
    assert np.allclose(np.asarray(scene.frames[1].T_world_cam)[0, 3], 0.2)
    assert scene.read_color(scene.frames[0]) is not None
    assert [(fid, round(pose[0, 3], 9)) for fid, pose in scene.skipped_poses] == [("000001", 0.1), ("000003", 0.3)]


def test_features_and_masks_come_from_their_folders(tmp_path: Path) -> None:
    src = _sequence(tmp_path / "seq", frames=2)
    (tmp_path / "f").mkdir()
    (tmp_path / "m").mkdir()
    np.save(tmp_path / "f" / "1.npy", np.ones((3, 4, 5), np.float32))
    cv2.imwrite(str(tmp_path / "m" / "000001.png"), np.full((H, W), 3, np.uint16))
    import_sevenscenes(src, tmp_path / "b", features=tmp_path / "f", masks=tmp_path / "m")
    scene = open_bundle(tmp_path / "b")
    assert scene.feature_dim == 5
    assert "placeholder" not in scene.name
    assert [f.id for f in scene.feature_frames] == [f.id for f in scene.mask_frames] == ["000001"]


def test_without_maps_the_bundle_has_colour_and_depth_for_the_run_to_compute_them(tmp_path: Path) -> None:
    src = _sequence(tmp_path / "seq", frames=1)
    import_sevenscenes(src, tmp_path / "b")
    scene = open_bundle(tmp_path / "b")
    assert not scene.feature_frames
    assert scene.feature_space == ""
    assert "placeholder" not in scene.name
    assert all(f.color is not None for f in scene.frames)
    (src / "camera-intrinsics.txt").unlink()
    with pytest.raises(InputError, match="camera-intrinsics"):
        import_sevenscenes(src, tmp_path / "c", placeholder_maps=True)


def test_the_cli_imports_the_layout(tmp_path: Path) -> None:
    src = _sequence(tmp_path / "seq", frames=3)
    argv = [sys.executable, "-m", "panogs_core.cli", "import", "sevenscenes", str(src), str(tmp_path / "b")]
    done = subprocess.run([*argv, "--placeholder-maps"], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "wrote 3 frames" in done.stdout
    assert len(open_bundle(tmp_path / "b").frames) == 3


def test_a_placeholder_bundle_carries_the_label_set_its_run_uses(tmp_path: Path) -> None:
    """The run's label set is the bundle's, in the placeholder space, and every primitive's feature is closest to
    ``surface`` (before, the run looked for CLIP embeddings of ScanNet-20 and refused the 8-d features)."""
    src = _sequence(tmp_path / "seq", frames=2)
    import_sevenscenes(src, tmp_path / "b", placeholder_maps=True)
    scene = open_bundle(tmp_path / "b")
    assert scene.feature_space == "placeholder"
    vocabulary = resolve_scene_vocabulary(scene, None)
    assert vocabulary.names == ("surface", "object")
    assert vocabulary.embeddings is not None
    feature = scene.read_features(scene.feature_frames[0]).reshape(-1)
    assert int(np.argmax(vocabulary.embeddings @ feature)) == 0


def test_a_vocabulary_is_refused_with_placeholder_maps(tmp_path: Path) -> None:
    src = _sequence(tmp_path / "seq", frames=1)
    vocabulary = Vocabulary(("chair",), ("thing",))
    with pytest.raises(InputError, match="vocabulary cannot be used with placeholder maps"):
        import_sevenscenes(src, tmp_path / "b", placeholder_maps=True, vocabulary=vocabulary)
    assert not (tmp_path / "b" / "scene.json").exists()


def test_a_failure_part_way_leaves_nothing_at_dst(tmp_path: Path) -> None:
    """Frame 2's depth is the wrong size: found only after two frames were written, in a staging folder."""
    src = _sequence(tmp_path / "seq")
    cv2.imwrite(str(src / "frame-000002.depth.png"), np.full((H, W + 1), 1500, np.uint16))
    dst = tmp_path / "out"
    dst.mkdir()  # an empty DST is allowed, and stays empty
    with pytest.raises(InputError, match=r"frame-000002\.depth\.png"):
        import_sevenscenes(src, dst, placeholder_maps=True)
    assert list(dst.iterdir()) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "seq"]
