"""The nerfstudio importer: the tiny room written as an ns-process-data folder (OpenGL transform_matrix, intrinsics
at twice the depth size, millimetre depth PNGs), imported back; then missing depth, distortion and missing files."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from capture_room import assert_points_agree, assert_same_cameras, write_nerfstudio

from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.capture import MapSources
from panogs_core.io.importers.nerfstudio import NerfstudioOptions, import_nerfstudio
from panogs_core.io.ply import write_ply

OPTIONS = NerfstudioOptions(maps=MapSources(placeholder_maps=True))


@pytest.fixture(scope="module")
def folder(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("nerfstudio") / "processed"
    write_nerfstudio(synth_tiny, src)
    return src


def _edit(folder: Path, dst: Path, change: object) -> Path:
    shutil.copytree(folder, dst)
    doc = json.loads((dst / "transforms.json").read_text())
    change(doc)  # type: ignore[operator]
    (dst / "transforms.json").write_text(json.dumps(doc))
    return dst


class TestImportNerfstudio:
    def test_smoke(self, folder: Path, synth_tiny: Path, tmp_path: Path) -> None:
        report = import_nerfstudio(folder, tmp_path / "b", OPTIONS)
        room, scene = open_bundle(synth_tiny), open_bundle(tmp_path / "b")
        assert report.frames_written == len(room.frames)
        pairs = [(f.id, r.id) for f, r in zip(scene.frames, room.frames)]
        assert_same_cameras(scene, room, pairs)
        assert_points_agree(scene, room, pairs)
        assert np.array_equal(scene.read_depth(scene.frames[5]), room.read_depth(room.frames[5]))
        assert not scene.has_geometry
        assert report.gravity_up == (0.0, 0.0, 1.0)

    def test_per_frame_intrinsics_and_ply(self, folder: Path, tmp_path: Path) -> None:
        def change(doc: dict) -> None:  # type: ignore[type-arg]
            for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
                value = doc.pop(key)
                for frame in doc["frames"]:
                    frame[key] = value
            doc["frames"][3]["fl_x"] *= 1.1  # another camera: dropped, a bundle has one
            doc["ply_file_path"] = "sparse_pc.ply"

        src = _edit(folder, tmp_path / "src", change)
        write_ply(src / "sparse_pc.ply", {k: np.arange(4, dtype=np.float32) for k in "xyz"})
        report = import_nerfstudio(src, tmp_path / "b", OPTIONS)
        assert dict(report.dropped)["intrinsics differ from the first frame's"] == ("000003",)
        scene = open_bundle(tmp_path / "b")
        assert scene.has_geometry
        assert "geometry.ply from the capture" in report.summary()

    def test_without_depth_the_message_says_how_to_get_it(self, folder: Path, tmp_path: Path) -> None:
        def change(doc: dict) -> None:  # type: ignore[type-arg]
            for frame in doc["frames"]:
                del frame["depth_file_path"]

        src = _edit(folder, tmp_path / "src", change)
        with pytest.raises(InputError, match=r"transforms\.json: no frame has a depth_file_path.*--use-depth"):
            import_nerfstudio(src, tmp_path / "b", OPTIONS)
        assert not (tmp_path / "b").exists()

    def test_distortion_is_refused(self, folder: Path, tmp_path: Path) -> None:
        src = _edit(folder, tmp_path / "src", lambda doc: doc.update(k1=-0.05))
        with pytest.raises(InputError, match=r"distortion coefficients.*k1"):
            import_nerfstudio(src, tmp_path / "b", OPTIONS)
        src = _edit(folder, tmp_path / "fish", lambda doc: doc.update(camera_model="OPENCV_FISHEYE"))
        with pytest.raises(InputError, match="OPENCV_FISHEYE"):
            import_nerfstudio(src, tmp_path / "b", OPTIONS)
        assert not (tmp_path / "b").exists()

    def test_missing_files_and_nan_pose_are_named(self, folder: Path, tmp_path: Path) -> None:
        def change(doc: dict) -> None:  # type: ignore[type-arg]
            doc["frames"][1]["depth_file_path"] = "depth/gone.png"
            doc["frames"][2]["file_path"] = "images/gone.png"
            doc["frames"][4]["transform_matrix"][0][3] = float("nan")

        src = _edit(folder, tmp_path / "src", change)
        report = import_nerfstudio(src, tmp_path / "b", OPTIONS)
        dropped = dict(report.dropped)
        assert [entry.split()[0] for entry in dropped["missing file"]] == ["000001", "000002"]
        assert "depth/gone.png" in dropped["missing file"][0]
        assert "images/gone.png" in dropped["missing file"][1]
        assert dropped["invalid pose (NaN, infinite or not a rotation)"] == ("000004",)
        assert "gone.png" in report.summary()

    def test_exception(self, folder: Path, tmp_path: Path) -> None:
        def change(doc: dict) -> None:  # type: ignore[type-arg]
            for frame in doc["frames"]:
                frame["depth_file_path"] = "depth/gone.png"

        src = _edit(folder, tmp_path / "src", change)
        with pytest.raises(InputError, match=r"depth/gone\.png"):
            import_nerfstudio(src, tmp_path / "b", OPTIONS)
        with pytest.raises(InputError, match=r"transforms\.json is missing"):
            import_nerfstudio(tmp_path, tmp_path / "b", OPTIONS)
        with pytest.raises(InputError, match="depth_unit"):
            NerfstudioOptions(depth_unit=0.0)
        assert not (tmp_path / "b").exists()
        assert not list(tmp_path.glob(".b.partial*"))
