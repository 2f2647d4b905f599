"""What the capture importers share: the motion rule, quaternions, the selection's checks, and a run of an imported
capture that labels the room as a run of the room itself does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from capture_room import export_maps, quaternion_xyzw, write_tum

from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.capture import FrameSelection, MapSources, keyframes_by_motion, quaternion_pose
from panogs_core.io.importers.tum import TumOptions, import_tum


def _turn_z(degrees: float) -> np.ndarray:  # (4, 4)
    a = np.radians(degrees)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


class TestKeyframesByMotion:
    def test_smoke(self) -> None:
        poses = [np.eye(4) for _ in range(6)]
        assert keyframes_by_motion(poses, 0.0, 0.0) == list(range(6))

    def test_feature(self) -> None:
        steps = [np.eye(4) for _ in range(7)]
        for i, T in enumerate(steps):
            T[0, 3] = 0.04 * i  # 4 cm a frame
        assert keyframes_by_motion(steps, 0.1, 90.0) == [0, 3, 6]  # 12 cm since the last kept, not since the last
        turns = [_turn_z(4.0 * i) for i in range(7)]
        assert keyframes_by_motion(turns, 1.0, 10.0) == [0, 3, 6]
        assert keyframes_by_motion([], 0.1, 1.0) == []

    def test_exception(self) -> None:
        with pytest.raises(InputError, match="stride"):
            FrameSelection(stride=0)
        with pytest.raises(InputError, match="min_translation"):
            FrameSelection(min_translation=-1.0)
        with pytest.raises(InputError, match="max_frames"):
            FrameSelection(max_frames=0)


class TestQuaternionPose:
    def test_feature(self) -> None:
        rng = np.random.default_rng(0)
        for _ in range(20):
            R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
            R *= np.sign(np.linalg.det(R))
            T = quaternion_pose(quaternion_xyzw(R), [1.0, 2.0, 3.0])
            assert np.allclose(T[:3, :3], R, atol=1e-12)
            assert np.allclose(T[:3, 3], [1, 2, 3])

    def test_exception(self) -> None:
        assert np.isnan(quaternion_pose(np.array([0.5, 0.5, 0.5, 0.2]), np.zeros(3))).all()
        assert np.isnan(quaternion_pose(np.array([np.nan, 0, 0, 1]), np.zeros(3))).all()


@pytest.mark.slow
def test_an_imported_capture_labels_the_room_as_the_room_itself(synth_tiny: Path, tmp_path: Path) -> None:
    """The room through TUM's files (depth / 5000, quaternions, shifted timestamps) and back runs to the same
    labels as the room itself, both with primitives from the depth (the TSDF path)."""
    from panogs_core.io.run_folder import load_run_labels
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import resolve_scene_vocabulary, run_pipeline

    room = open_bundle(synth_tiny)
    stamps = write_tum(synth_tiny, tmp_path / "seq")
    cam = room.camera
    (tmp_path / "K.txt").write_text(f"{cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}")
    features, masks = export_maps(room, [f"{t:.6f}" for t in stamps], tmp_path / "maps")
    vocabulary = resolve_scene_vocabulary(room, None)
    maps = MapSources(features=features, masks=masks, feature_space=room.feature_space, vocabulary=vocabulary)
    import_tum(tmp_path / "seq", tmp_path / "b", TumOptions(intrinsics=tmp_path / "K.txt", maps=maps))
    cfg = PipelineConfig().with_overrides(
        {"primitives": {"use_geometry": False, "target_spacing": 0.05}, "appearance": {"iterations": 2}}
    )
    run_pipeline(synth_tiny, tmp_path / "direct", cfg)
    run_pipeline(tmp_path / "b", tmp_path / "imported", cfg)
    direct, imported = load_run_labels(tmp_path / "direct"), load_run_labels(tmp_path / "imported")
    assert direct.vocabulary.names == imported.vocabulary.names
    assert len(direct.points) == len(imported.points)
    assert np.allclose(direct.points, imported.points, atol=1e-4)
    assert np.array_equal(direct.semantic, imported.semantic)
    assert np.array_equal(direct.instance, imported.instance)
