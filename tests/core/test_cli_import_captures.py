"""``panogs import nerfstudio | record3d | tum``: the tiny room written in each capture's layout, imported through
the command line as a user types it (``panogs_core.cli.main``): each subcommand's own options, the frame selection
and maps options, the summary with the next command, and bad input as one message naming the file, exit 2."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from capture_room import export_maps, write_nerfstudio, write_record3d, write_tum

from panogs_core.cli import build_parser
from panogs_core.cli.commands.import_sources import IMPORT_SOURCES
from panogs_core.cli.main import main as cli_main
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.sources import CAPTURE_SOURCES
from panogs_core.io.importers.tum import FREIBURG_CAMERAS

# What every capture source takes: the command's own, the frame selection, the maps and the name.
CAPTURE_SHARED = {
    "-h",
    "--help",
    "--stride",
    "--vocabulary",
    "--feature-space",
    "--min-translation",
    "--min-rotation",
    "--max-frames",
    "--features",
    "--masks",
    "--placeholder-maps",
    "--name",
}
OWN = {
    "nerfstudio": {"--depth-unit", "--no-ply"},
    "record3d": {"--min-confidence"},
    "tum": {"--intrinsics", "--camera", "--max-time-difference", "--depth-scale"},
}


def _parsers() -> dict[str, argparse.ArgumentParser]:
    (top,) = (a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    (sources,) = (a for a in top.choices["import"]._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sources.choices)


def _import(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = cli_main(["import", *argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def tum(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("tum") / "rgbd_dataset_room"
    write_tum(synth_tiny, src)
    cam = open_bundle(synth_tiny).camera
    (src / "intrinsics.txt").write_text(f"{cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n")
    return src


@pytest.fixture(scope="module")
def record3d(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("record3d") / "2026-05-01--10-12-44"
    write_record3d(synth_tiny, src)
    return src


@pytest.fixture(scope="module")
def nerfstudio(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("nerfstudio") / "processed"
    write_nerfstudio(synth_tiny, src)
    return src


def test_each_capture_source_is_one_entry_with_only_its_own_options() -> None:
    parsers = _parsers()
    for name, own in OWN.items():
        options = {o for a in parsers[name]._actions for o in a.option_strings}
        assert options == CAPTURE_SHARED | own, name
        cli = CAPTURE_SOURCES[name].cli
        (entry,) = (s for s in IMPORT_SOURCES if s.name == name)
        assert (entry.help, entry.example, entry.description) == (cli.help, cli.example, cli.description)
        text = parsers[name].format_help()
        assert "example:" in text
        assert cli.example in text
        assert "--min-rotation" in text  # the key-frame rule is every capture's


def test_the_camera_choices_are_the_freiburg_cameras() -> None:
    (camera,) = (o for o in CAPTURE_SOURCES["tum"].cli.options if o.flag == "--camera")
    assert camera.choices == tuple(FREIBURG_CAMERAS)


def test_tum_imports_with_features_masks_and_stride(
    tum: Path, synth_tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tum
    room = open_bundle(synth_tiny)
    stems = sorted(p.stem for p in (src / "depth").glob("*.png"))  # maps are named as the depth images
    features, masks = export_maps(room, stems, tmp_path / "maps")
    dst = tmp_path / "fr_room"
    argv = ["tum", str(src), str(dst), "--intrinsics", str(src / "intrinsics.txt"), "--stride", "2"]
    argv += ["--features", str(features), "--masks", str(masks), "--feature-space", "minilm-l6"]
    code, out, err = _import(argv, capsys)
    assert code == 0, err
    kept = len(room.frames[::2])
    assert out.startswith(f"wrote {kept} of {len(room.frames)} frames to {dst}")
    assert f"next: panogs run {dst} --out {dst}-run" in out
    scene = open_bundle(dst)
    assert len(scene.frames) == kept
    assert np.allclose(np.asarray(scene.frames[1].T_world_cam), np.asarray(room.frames[2].T_world_cam), atol=1e-5)
    assert np.array_equal(scene.read_masks(scene.frames[1]), room.read_masks(room.frames[2]))


def test_record3d_imports_with_the_motion_rule_and_a_frame_cap(
    record3d: Path, synth_tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = len(open_bundle(synth_tiny).frames)
    dst = tmp_path / "kitchen"
    argv = ["record3d", str(record3d), str(dst), "--placeholder-maps", "--min-confidence", "2", "--max-frames", "3"]
    code, out, err = _import(argv, capsys)
    assert code == 0, err
    assert out.startswith(f"wrote 3 of {frames} frames to {dst}")
    assert "2D maps: placeholders" in out
    assert len(open_bundle(dst).frames) == 3
    # A key-frame rule no step of the room reaches keeps only the first frame.
    motion = ["--min-translation", "100", "--min-rotation", "360"]
    code, out, err = _import(["record3d", str(record3d), str(tmp_path / "k2"), "--placeholder-maps", *motion], capsys)
    assert code == 0, err
    assert out.startswith(f"wrote 1 of {frames} frames")


def test_nerfstudio_imports_with_its_depth_unit(
    nerfstudio: Path, synth_tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    room = open_bundle(synth_tiny)
    dst = tmp_path / "living_room"
    code, out, err = _import(["nerfstudio", str(nerfstudio), str(dst), "--placeholder-maps", "--name", "lr"], capsys)
    assert code == 0, err
    assert out.startswith(f"wrote {len(room.frames)} of {len(room.frames)} frames to {dst}")
    scene = open_bundle(dst)
    assert scene.name.startswith("lr")
    depth = scene.read_depth(scene.frames[1])
    # Millimetre PNGs read as metres by default; --depth-unit 0.002 reads the same files as twice as far.
    code, _, err = _import(
        ["nerfstudio", str(nerfstudio), str(tmp_path / "far"), "--placeholder-maps", "--depth-unit", "0.002"], capsys
    )
    assert code == 0, err
    far = open_bundle(tmp_path / "far").read_depth(open_bundle(tmp_path / "far").frames[1])
    valid = depth > 0
    assert np.allclose(far[valid], 2 * depth[valid], rtol=1e-3)


def test_tum_without_intrinsics_or_camera_says_which(
    tum: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tum
    code, out, err = _import(["tum", str(src), str(tmp_path / "b"), "--placeholder-maps"], capsys)
    assert code == 2
    assert "--intrinsics" in err
    assert "--camera" in err
    assert "Traceback" not in err
    assert out == ""
    assert not (tmp_path / "b").exists()


def test_tum_with_a_missing_depth_list_names_the_file(
    tum: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "seq"
    shutil.copytree(tum, src)
    (src / "depth.txt").unlink()
    code, _, err = _import(["tum", str(src), str(tmp_path / "b"), "--camera", "freiburg1"], capsys)
    assert code == 2
    assert str(src / "depth.txt") in err
    assert "Traceback" not in err
    assert not (tmp_path / "b").exists()


def test_record3d_with_a_truncated_exr_names_it_and_writes_nothing(
    record3d: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "capture"
    shutil.copytree(record3d, src)
    for exr in (src / "depth").glob("*.exr"):
        if exr.name != "0.exr":
            exr.unlink()
    (src / "depth" / "0.exr").write_bytes((src / "depth" / "0.exr").read_bytes()[:200])
    code, _, err = _import(["record3d", str(src), str(tmp_path / "b"), "--placeholder-maps"], capsys)
    assert code == 2
    assert "0.exr" in err
    assert "Traceback" not in err
    assert not (tmp_path / "b").exists()
    assert not list(tmp_path.glob(".b.partial*"))


def test_nerfstudio_with_a_missing_depth_file_names_it(
    nerfstudio: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "processed"
    shutil.copytree(nerfstudio, src)
    doc = json.loads((src / "transforms.json").read_text())
    for frame in doc["frames"]:
        frame["depth_file_path"] = "depth/gone.png"
    (src / "transforms.json").write_text(json.dumps(doc))
    code, _, err = _import(["nerfstudio", str(src), str(tmp_path / "b"), "--placeholder-maps"], capsys)
    assert code == 2
    assert "depth/gone.png" in err
    assert "Traceback" not in err
    assert not (tmp_path / "b").exists()


def test_an_out_of_range_value_is_refused_before_anything_is_read(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _import(["tum", "nowhere", "b", "--camera", "freiburg1", "--stride", "0"], capsys)
    assert code == 2
    assert "stride must be >= 1" in err
    with pytest.raises(SystemExit) as exit_:
        cli_main(["import", "record3d", "a", "b", "--min-confidence", "3"])
    assert exit_.value.code == 2
    assert "invalid choice: 3" in capsys.readouterr().err


def test_building_the_parser_loads_no_numeric_library() -> None:
    """Why the capture sources' text lives apart from their importers: ``panogs --help`` stays quick."""
    code = "import sys; from panogs_core.cli import build_parser; build_parser(); "
    code += "print(sorted({'numpy', 'cv2'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120).stdout
    assert out.strip() == "[]"
