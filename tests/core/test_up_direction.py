"""The capture's up direction and renders from any capture frame: the tiny room captured in a tilted world,
imported with and without the source's gravity and run; the run's up is the room's z turned with the world, and
``panogs render --frame`` reaches the frames the import's stride left out."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from capture_room import TILTED_55, export_maps, tilted_world, write_record3d
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture)

from panogs_core.cli import main as cli_main
from panogs_core.errors import BundleError
from panogs_core.gaussians.config import AppearanceConfig
from panogs_core.io.bundle import open_bundle
from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.io.importers.capture import MapSources
from panogs_core.io.importers.record3d import Record3DOptions, import_record3d
from panogs_core.io.ply import read_ply_vertices
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.run import run_pipeline
from panogs_core.stages.up_direction import UpDirection, camera_up, floor_normal, run_up
from panogs_core.types import Camera

TILT = TILTED_55  # the room's z-up ends up 55 degrees from every world axis it had
NO_FIT = PipelineConfig(appearance=AppearanceConfig(enabled=False))
CAMERA = Camera(width=8, height=6, fx=5.0, fy=5.0, cx=3.5, cy=2.5)


def _degrees(a: object, b: object) -> float:
    u, v = np.asarray(a, float), np.asarray(b, float)
    cos = float(u @ v / np.linalg.norm(u) / np.linalg.norm(v))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _cameras(run: Path) -> dict:
    return json.loads((run / "cameras.json").read_text())


@pytest.fixture
def tilted_run(tilted_tum_run: Path) -> Path:
    """The room as a TUM sequence in the tilted world (TUM records no gravity), every 2nd frame imported, run
    (the session's, shared with the viewer's test: only read)."""
    return tilted_tum_run


def test_a_tilted_capture_without_gravity_gets_the_floor_as_up(tilted_run: Path) -> None:
    root = tilted_run
    assert open_bundle(root / "bundle").up is None
    cameras = _cameras(root / "run")
    assert cameras["up_source"] == "floor"
    assert _degrees(cameras["up"], TILT[:3, 2]) < 3.0
    assert abs(np.linalg.norm(cameras["up"]) - 1.0) < 1e-5


def test_render_from_a_frame_the_stride_left_out(tilted_run: Path, synth_tiny: Path, tmp_path: Path) -> None:
    root = tilted_run
    bundle = open_bundle(root / "bundle")
    skipped = dict(bundle.skipped_poses)
    assert len(skipped) == len(open_bundle(synth_tiny).frames) - len(bundle.frames) > 0
    listed = {f["id"]: f for f in _cameras(root / "run")["frames"]}
    assert all(listed[i].get("skipped") is True for i in skipped)
    assert not any(listed[f.id].get("skipped") for f in bundle.frames)
    room = open_bundle(synth_tiny)
    index = [f.id for f in open_bundle(root / "bundle").frames]
    order = sorted([*index, *skipped], key=float)
    frame_id = next(i for i in order if i in skipped)
    room_frame = room.frames[order.index(frame_id)]
    np.testing.assert_allclose(skipped[frame_id], TILT @ room_frame.T_world_cam, atol=1e-6)
    assert cli_main(["render", str(root / "run"), "--frame", frame_id, "--out", str(tmp_path / "by-frame")]) == 0
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"T_world_cam": (TILT @ room_frame.T_world_cam).tolist()}))
    assert cli_main(["render", str(root / "run"), "--pose", str(pose), "--out", str(tmp_path / "by-pose")]) == 0
    for name in ("color.png", "depth.png", "semantic.png"):
        assert (tmp_path / "by-frame" / name).read_bytes() == (tmp_path / "by-pose" / name).read_bytes()
    # The render sees what the capture's own frame saw: its depth agrees with the frame's depth image.
    rendered = cv2.imread(str(tmp_path / "by-frame" / "depth.png"), cv2.IMREAD_UNCHANGED) / 1000.0
    truth = room.read_depth(room_frame)
    both = (rendered > 0) & (truth > 0)
    assert both.mean() > 0.5
    assert np.median(np.abs(rendered[both] - truth[both])) < 0.05


def test_gravity_from_the_source_is_stored_and_used(synth_tiny: Path, tmp_path: Path) -> None:
    # ARKit's world is +Y up: the room turned so that its z becomes +Y, as Record3D writes it.
    upright = tilted_world((1.0, 0.0, 0.0), -90.0)
    write_record3d(synth_tiny, tmp_path / "r3d", world=upright)
    room = open_bundle(synth_tiny)
    stems = [str(n) for n in range(len(room.frames))]
    features, masks = export_maps(room, stems, tmp_path / "maps")
    maps = MapSources(features=features, masks=masks, feature_space=room.feature_space, vocabulary=room.vocabulary)
    report = import_record3d(tmp_path / "r3d", tmp_path / "bundle", Record3DOptions(maps=maps))
    assert "scene.json up" in report.summary()
    assert json.loads((tmp_path / "bundle" / "scene.json").read_text())["up"] == [0.0, 1.0, 0.0]
    run_pipeline(tmp_path / "bundle", tmp_path / "run", NO_FIT)
    cameras = _cameras(tmp_path / "run")
    assert (cameras["up"], cameras["up_source"]) == ([0.0, 1.0, 0.0], "bundle")
    # Without the source's word, the estimate from the same run's normals and poses finds the same up.
    vertices = read_ply_vertices(tmp_path / "run" / "gaussians.ply")
    normals = np.stack([vertices[k] for k in ("nx", "ny", "nz")], axis=1)
    poses = [np.asarray(f["T_world_cam"]) for f in cameras["frames"]]
    assert run_up(None, poses, normals) == UpDirection((0.0, 1.0, 0.0), "floor")


def test_up_in_scene_json_is_validated_and_normalised(tmp_path: Path) -> None:
    def bundle(up: object, skipped: object = None) -> Path:
        root = tmp_path / f"b{len(list(tmp_path.iterdir()))}"
        with BundleWriter(root, name="t", camera=CAMERA, feature_dim=4, feature_space="test") as w:
            features, masks = np.ones((3, 4, 4), np.float32), np.ones((6, 8), np.int32)
            w.add_frame("0", np.eye(4), np.ones((6, 8)), features=features, masks=masks)
        doc = json.loads((root / "scene.json").read_text())
        doc["up"] = up
        if skipped is not None:
            doc["skipped_frames"] = skipped
        (root / "scene.json").write_text(json.dumps(doc))
        return root

    assert open_bundle(bundle([0, 0, 2])).up == (0.0, 0.0, 1.0)
    for bad in ([0, 0, 0], [1, 2], "up", [1, None, 0], [True, 0, 0]):
        with pytest.raises(BundleError, match=r"scene\.json: up"):
            open_bundle(bundle(bad))
    with pytest.raises(BundleError, match=r"skipped_frames\[0\]\.id: '0' used by another frame"):
        open_bundle(bundle([0, 0, 1], [{"id": "0", "pose": np.eye(4).tolist()}]))
    with pytest.raises(BundleError, match=r"skipped_frames\[0\]\.pose: contains NaN"):
        open_bundle(bundle([0, 0, 1], [{"id": "1", "pose": [[float("nan")] * 4] * 4}]))
    scene = open_bundle(bundle([0, 1, 0], [{"id": "1", "pose": np.eye(4).tolist()}]))
    assert [i for i, _ in scene.skipped_poses] == ["1"]


def test_the_estimate_falls_back_to_the_cameras_and_follows_their_sign() -> None:
    level = np.eye(4)
    level[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along +y with z up
    walls = np.array([[1.0, 0, 0], [0, 1.0, 0]] * 50)
    assert run_up(None, [level], walls).source == "cameras"  # no horizontal surface: the cameras' guess
    floor = np.concatenate([walls, np.tile([0.05, 0.0, -1.0], (20, 1))])  # unoriented, a little tilted
    found = floor_normal(floor, camera_up([level]))
    assert found is not None
    assert _degrees(found, [-0.05, 0, 1]) < 1e-3  # the sign the camera's up gives
    assert run_up((0, 0, 3), [level], floor).up == (0.0, 0.0, 1.0)
    tilted = run_up(None, [level], floor)  # 2.9 degrees off z: kept as found
    assert tilted.source == "floor"
    assert _degrees(tilted.up, [-0.05, 0, 1]) < 1e-3
    nearly = np.concatenate([walls, np.tile([0.02, 0.0, 1.0], (20, 1))])  # 1.1 degrees off z: z itself
    assert run_up(None, [level], nearly).up == (0.0, 0.0, 1.0)
