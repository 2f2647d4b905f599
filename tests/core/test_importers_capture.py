"""What the capture importers share: the motion rule, quaternions, the selection's checks, and a run of an imported
capture that labels the room as a run of the room itself does."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from capture_room import export_maps, quaternion_xyzw, write_tum

from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.capture import FrameSelection, MapSources, keyframes_by_motion, quaternion_pose
from panogs_core.io.importers.sources import CAPTURE_SOURCES, SourceCli, options_from_values
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

    def test_a_threshold_of_zero_leaves_its_test_out(self) -> None:
        # A hand-held camera always turns a little: with only a translation threshold, that must keep nothing.
        jitter = []
        for i in range(6):
            angle = np.radians(0.01 * (i % 2))
            pose = np.eye(4)
            pose[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
            pose[0, 3] = 0.04 * i
            jitter.append(pose)
        assert keyframes_by_motion(jitter, 0.1, 0.0) == [0, 3]
        assert keyframes_by_motion(jitter, 0.0, 5.0) == [0]

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


def _parser(cli: SourceCli) -> argparse.ArgumentParser:
    """An argparse subcommand built from the table alone, as the command line would."""
    parser = argparse.ArgumentParser(prog=f"panogs import {cli.name}", description=cli.description)
    parser.add_argument("src")
    parser.add_argument("dst")
    types: dict[str, Any] = {"int": int, "float": float, "str": str, "path": str}
    for opt in cli.options:
        dest = opt.field.replace(".", "__")
        if opt.kind in ("switch", "switch_off"):
            action = "store_true" if opt.kind == "switch" else "store_false"
            parser.add_argument(opt.flag, dest=dest, action=action, default=opt.default, help=opt.help)
        else:
            kw: dict[str, Any] = {"choices": list(opt.choices)} if opt.choices else {}
            parser.add_argument(opt.flag, dest=dest, type=types[opt.kind], default=opt.default, help=opt.help, **kw)
    return parser


class TestSourceTable:
    @pytest.mark.parametrize("source", sorted(CAPTURE_SOURCES))
    def test_defaults_are_the_options_defaults(self, source: str) -> None:
        entry = CAPTURE_SOURCES[source]
        args = vars(_parser(entry.cli).parse_args(["SRC", "DST"]))
        values = {k.replace("__", "."): v for k, v in args.items() if k not in ("src", "dst")}
        values["maps.vocabulary"] = None  # the command line resolves a name or file first
        assert options_from_values(entry.options, values) == entry.options()

    @pytest.mark.parametrize("source", sorted(CAPTURE_SOURCES))
    def test_the_example_parses(self, source: str) -> None:
        entry = CAPTURE_SOURCES[source]
        words = shlex.split(entry.cli.example)
        assert words[:3] == ["panogs", "import", source]
        args = vars(_parser(entry.cli).parse_args(words[3:]))
        values = {k.replace("__", "."): v for k, v in args.items() if k not in ("src", "dst")}
        opts = options_from_values(entry.options, values)
        assert opts.maps.placeholder_maps

    def test_exception(self) -> None:
        with pytest.raises(InputError, match="no field colour"):
            options_from_values(TumOptions, {"colour": 1})
        with pytest.raises(InputError, match="unknown option field"):
            options_from_values(TumOptions, {"frames.stride": 1})
        with pytest.raises(InputError, match="stride"):
            options_from_values(TumOptions, {"selection.stride": 0})


@pytest.mark.slow
def test_an_imported_capture_labels_the_room_as_the_room_itself(synth_tiny: Path, tmp_path: Path) -> None:
    """The room through TUM's files (depth / 5000, quaternions as text, shifted timestamps) and back runs to the
    labels of the room itself, both with primitives from the depth (the TSDF path) and the same vocabulary: the same
    points and the same labels, exactly.

    The ground truth is written with 17 decimals, so that the only loss is the importer's (it keeps the poses in
    float64 from the text to ``scene.json``). With 9 decimals the poses move by about 1e-9, the TSDF points by
    float32 rounding (5e-7 m), and the super-primitive graph cut is not stable under that: 99.7 % of the semantic
    labels equal, instance partitions 97.5 % pure (tiny / seed 0, 2026-12-05); with 17, all equal.
    """
    from panogs_core.io.run_folder import load_run_labels
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import resolve_scene_vocabulary, run_pipeline

    room = open_bundle(synth_tiny)
    stamps = write_tum(synth_tiny, tmp_path / "seq", decimals=17)
    cam = room.camera
    (tmp_path / "K.txt").write_text(f"{cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}")
    features, masks = export_maps(room, [f"{t:.6f}" for t in stamps], tmp_path / "maps")
    vocabulary = resolve_scene_vocabulary(room, None)
    maps = MapSources(features=features, masks=masks, feature_space=room.feature_space, vocabulary=vocabulary)
    import_tum(tmp_path / "seq", tmp_path / "b", TumOptions(intrinsics=tmp_path / "K.txt", maps=maps))
    cfg = PipelineConfig().with_overrides(
        {"primitives": {"use_geometry": False, "target_spacing": 0.05}, "appearance": {"enabled": False}}
    )  # the labels are written before the appearance fit and read nothing of it (panogs_core/pipeline/run.py)
    run_pipeline(synth_tiny, tmp_path / "direct", cfg, vocabulary=vocabulary)
    run_pipeline(tmp_path / "b", tmp_path / "imported", cfg, vocabulary=vocabulary)
    direct, imported = load_run_labels(tmp_path / "direct"), load_run_labels(tmp_path / "imported")
    assert direct.vocabulary.names == imported.vocabulary.names
    np.testing.assert_array_equal(direct.points, imported.points)
    np.testing.assert_array_equal(direct.semantic, imported.semantic)
    np.testing.assert_array_equal(direct.instance, imported.instance)


def test_a_failed_scannet_import_leaves_nothing_at_dst(tmp_path: Path) -> None:
    """The research importers share the staged write: a frame that fails half-way removes the whole bundle."""
    from test_importers import _scannet

    from panogs_core.io.importers.scannet import import_scannet

    src = _scannet(tmp_path / "scan", n=4, bad_pose=-1)
    (src / "depth" / "2.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)  # a PNG header, no image
    with pytest.raises(InputError, match=r"2\.png"):
        import_scannet(src, tmp_path / "b")
    assert not (tmp_path / "b").exists()
    assert not list(tmp_path.glob(".b.partial*"))
    report = import_scannet(_scannet(tmp_path / "good", n=3, bad_pose=-1), tmp_path / "c")
    assert report.bundle == tmp_path / "c"
    assert open_bundle(report.bundle).frames
