"""Bundle writer, validator and archive extraction: a valid bundle opens; every broken rule is reported."""

from __future__ import annotations

import errno
import gc
import io
import json
import os
import shutil
import struct
import tarfile
import warnings
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

import panogs_core.io.bundle.file_checks
from panogs_core.bounded_json import JsonLimits
from panogs_core.errors import BundleError, InputError
from panogs_core.io.bundle import FORMAT_ID, Bundle, BundleLimits, open_bundle
from panogs_core.io.bundle.archive import extract_archive
from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.types import Camera, Vocabulary

CAM = Camera(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
DIM = 8
NUM_VERTICES = 20


def _pose(angle: float, t: tuple[float, float, float]) -> np.ndarray:  # (4, 4)
    c, s = np.cos(angle), np.sin(angle)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose[:3, 3] = t
    return pose


def _write_valid(root: Path) -> Path:
    """3 frames 64x48, D=8: frame 0 has everything, frame 1 no masks, frame 2 no colour nor features."""
    rng = np.random.default_rng(0)
    w = BundleWriter(root, name="tiny", camera=CAM, feature_dim=DIM, feature_space="test-space")
    for i in range(3):
        depth = rng.uniform(0.5, 3.0, (CAM.height, CAM.width))
        depth[0, 0] = 0.0
        color = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) if i < 2 else None
        features = rng.normal(size=(6, 8, DIM)).astype(np.float16) if i < 2 else None
        masks = rng.integers(0, 4, (CAM.height, CAM.width)) if i != 1 else None
        w.add_frame(f"{i:06d}", _pose(0.1 * i, (i, 0, 0)), depth, color=color, features=features, masks=masks)
    w.write_geometry(rng.normal(size=(NUM_VERTICES, 3)), colors=rng.uniform(size=(NUM_VERTICES, 3)))
    emb = rng.normal(size=(3, DIM))
    w.write_vocabulary(Vocabulary(("wall", "chair", "table"), ("stuff", "thing", "thing"), emb))
    w.write_ground_truth(rng.integers(-1, 3, NUM_VERTICES), rng.integers(-1, 5, NUM_VERTICES))
    return w.close()


@pytest.fixture
def bundle_dir(tmp_path: Path) -> Path:
    return _write_valid(tmp_path / "scene")


def _manifest(root: Path) -> dict[str, Any]:
    return json.loads((root / "scene.json").read_text())  # type: ignore[no-any-return]


def _save(root: Path, doc: dict[str, Any]) -> None:
    (root / "scene.json").write_text(json.dumps(doc))


def _edit(change: Callable[[dict[str, Any]], None]) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        doc = _manifest(root)
        change(doc)
        _save(root, doc)

    return apply


def _problems(root: Path) -> list[str]:
    with pytest.raises(BundleError) as info:
        open_bundle(root)
    return info.value.problems


class TestOpenValid:
    def test_smoke(self, bundle_dir: Path) -> None:
        scene = open_bundle(bundle_dir)
        assert isinstance(scene, Bundle)
        assert scene.name == "tiny"
        assert scene.camera == CAM
        assert (scene.feature_dim, scene.feature_space, scene.depth_scale) == (DIM, "test-space", 1000.0)
        assert [f.id for f in scene.frames] == ["000000", "000001", "000002"]
        assert [f.id for f in scene.feature_frames] == ["000000", "000001"]
        assert [f.id for f in scene.mask_frames] == ["000000", "000002"]
        assert scene.has_geometry
        assert scene.has_ground_truth

    def test_read_methods(self, bundle_dir: Path) -> None:
        scene = open_bundle(bundle_dir)
        f0, f2 = scene.frames[0], scene.frames[2]
        depth = scene.read_depth(f0)
        assert depth.shape == (48, 64)
        assert depth.dtype == np.float32
        assert depth[0, 0] == 0.0
        assert 0.5 <= depth[1, 1] <= 3.0
        color = scene.read_color(f0)
        assert color is not None
        assert color.shape == (48, 64, 3)  # resampled from 32x24
        assert color.dtype == np.uint8
        assert scene.read_color(f2) is None
        feats = scene.read_features(f0)
        assert feats.shape == (6, 8, DIM)
        assert feats.dtype == np.float16
        masks = scene.read_masks(f0)
        assert masks.dtype == np.int32
        assert masks.shape == (48, 64)
        with pytest.raises(InputError, match="no masks"):
            scene.read_masks(scene.frames[1])
        np.testing.assert_allclose(scene.frames[1].T_world_cam, _pose(0.1, (1, 0, 0)))

    def test_depth_round_trip_in_millimetres(self, tmp_path: Path) -> None:
        w = BundleWriter(tmp_path, name="d", camera=CAM, feature_dim=2, feature_space="s")
        depth = np.full((48, 64), 1.2344)
        depth[0, :3] = [np.nan, -1.0, 70.0]  # invalid, invalid, beyond uint16 at 1000 per metre
        w.add_frame("a", np.eye(4), depth, features=np.zeros((2, 2, 2), np.float32), masks=np.ones((4, 4), int))
        scene = open_bundle(w.close())
        out = scene.read_depth(scene.frames[0])
        assert out[1, 1] == pytest.approx(1.234, abs=1e-6)
        assert out[0, :3].tolist() == pytest.approx([0.0, 0.0, 65.535])

    def test_geometry_and_ground_truth(self, bundle_dir: Path) -> None:
        scene = open_bundle(bundle_dir)
        geo = scene.read_geometry()
        assert geo is not None
        assert geo.points.shape == (NUM_VERTICES, 3)
        assert geo.colors is not None
        assert 0.0 <= geo.colors.min() <= geo.colors.max() <= 1.0
        gt = scene.read_ground_truth()
        assert gt is not None
        assert gt.semantic.dtype == np.int64
        assert gt.semantic.shape == (NUM_VERTICES,)
        assert gt.points is None
        vocab = scene.vocabulary
        assert vocab is not None
        assert vocab.kinds == ("stuff", "thing", "thing")
        assert vocab.embeddings is not None
        np.testing.assert_allclose(np.linalg.norm(vocab.embeddings, axis=1), 1.0, rtol=1e-5)

    def test_jpeg_with_trailer_after_end_marker(self, bundle_dir: Path) -> None:
        path = bundle_dir / "color" / "000000.jpg"
        path.write_bytes(path.read_bytes() + b"\x00trailer appended by a phone" * 40)
        scene = open_bundle(bundle_dir)
        color = scene.read_color(scene.frames[0])
        assert color is not None

    def test_optional_files_absent(self, bundle_dir: Path) -> None:
        for name in ("geometry.ply", "vocabulary.json", "vocabulary.npy"):
            (bundle_dir / name).unlink()
        shutil.rmtree(bundle_dir / "gt")
        scene = open_bundle(bundle_dir)
        assert scene.read_geometry() is None
        assert scene.read_ground_truth() is None
        assert scene.vocabulary is None

    def test_ground_truth_with_points_needs_no_geometry(self, bundle_dir: Path) -> None:
        (bundle_dir / "geometry.ply").unlink()
        np.savez(
            bundle_dir / "gt" / "labels.npz",
            semantic=np.array([0, 1, -1]),
            instance=np.array([-1, 0, 1]),
            points=np.zeros((3, 3), np.float32),
        )
        gt = open_bundle(bundle_dir).read_ground_truth()
        assert gt is not None
        assert gt.points is not None
        assert gt.points.shape == (3, 3)


def _truncate(rel: str, keep: float = 0.5) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        data = (root / rel).read_bytes()
        (root / rel).write_bytes(data[: int(len(data) * keep)])

    return apply


def _replace_image(rel: str, image: np.ndarray) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        assert cv2.imwrite(str(root / rel), image)

    return apply


def _replace_npy(rel: str, array: np.ndarray, *, pickle: bool = False) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        np.save(root / rel, array, allow_pickle=pickle)

    return apply


def _symlink_depth(root: Path) -> None:
    target = root.parent / "outside.png"
    shutil.copy(root / "depth/000001.png", target)
    (root / "depth/000001.png").unlink()
    os.symlink(target, root / "depth/000001.png")


def _symlink_folder(root: Path) -> None:
    shutil.move(root / "masks", root.parent / "masks_elsewhere")
    os.symlink(root.parent / "masks_elsewhere", root / "masks")


def _set_gt(**arrays: np.ndarray) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        np.savez(root / "gt" / "labels.npz", **arrays)

    return apply


def _set(path: list[Any], value: Any) -> Callable[[dict[str, Any]], None]:
    def change(doc: dict[str, Any]) -> None:
        node = doc
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return change


def _bad_rotation(doc: dict[str, Any]) -> None:
    doc["frames"][1]["pose"][0][0] = 1.2


def _drop_key(key: str) -> Callable[[dict[str, Any]], None]:
    def change(doc: dict[str, Any]) -> None:
        for frame in doc["frames"]:
            frame.pop(key, None)

    return change


def _nested(levels: int) -> Any:
    value: Any = 1
    for _ in range(levels):
        value = [value]
    return value


def _raw_manifest_edit(old: str, new: str) -> Callable[[Path], None]:
    def apply(root: Path) -> None:  # on the text: json.dumps cannot write an integer of 5,000 digits
        text = (root / "scene.json").read_text()
        assert old in text
        (root / "scene.json").write_text(text.replace(old, new, 1))

    return apply


def _jpeg_as(rel: str) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        ok, data = cv2.imencode(".jpg", np.zeros((48, 64), np.uint8))
        assert ok
        (root / rel).write_bytes(data.tobytes())

    return apply


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _declared_png(width: int, height: int, bit_depth: int = 16) -> bytes:
    """A PNG whose header declares ``width`` x ``height`` grey pixels, with one row of data (a decoder would
    allocate the whole image before finding the rest missing)."""
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, 0, 0, 0, 0)
    row = zlib.compress(b"\x00" + b"\x00" * (width * bit_depth // 8))
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", row) + _png_chunk(b"IEND", b"")


_GRAY = np.zeros((24, 32), np.uint8)
_SMALL_DEPTH = np.ones((24, 32), np.uint16)
_NAN_POSE = [[float("nan"), 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]

BROKEN: list[tuple[str, Callable[[Path], object], str]] = [
    ("no manifest", lambda r: (r / "scene.json").unlink(), "scene.json: missing"),
    ("bad json", lambda r: (r / "scene.json").write_text("{nope"), "scene.json: not valid JSON"),
    ("manifest not object", lambda r: (r / "scene.json").write_text("[1]"), "expected an object"),
    ("format id", _edit(_set(["format"], "panogs-scene/2")), "scene.json: format 'panogs-scene/2'"),
    ("fx negative", _edit(_set(["camera", "fx"], -5)), "camera.fx -5"),
    ("width float", _edit(_set(["camera", "width"], 64.5)), "camera.width 64.5"),
    ("cy missing", _edit(lambda d: d["camera"].pop("cy")), "camera.cy None"),
    ("fy infinite", _edit(_set(["camera", "fy"], float("inf"))), "camera.fy inf"),
    ("depth scale", _edit(_set(["depth_scale"], 0)), "depth_scale 0"),
    ("feature dim", _edit(_set(["features", "dim"], 0)), "features.dim 0"),
    ("feature space", _edit(lambda d: d["features"].pop("space")), "features.space None"),
    ("no frames", _edit(_set(["frames"], [])), "frames [], expected a non-empty list"),
    ("duplicate id", _edit(_set(["frames", 2, "id"], "000000")), "frames[2].id: '000000' used by an earlier"),
    ("nan pose", _edit(_set(["frames", 1, "pose"], _NAN_POSE)), "frames[1].pose: contains NaN"),
    ("pose shape", _edit(_set(["frames", 0, "pose"], [[1, 0], [0, 1]])), "frames[0].pose: [[1, 0], [0, 1]]"),
    ("rotation", _edit(_bad_rotation), "frames[1].pose: rotation not orthonormal"),
    ("reflection", _edit(_set(["frames", 0, "pose", 2, 2], -1.0)), "det = -1.0000"),
    ("last row", _edit(_set(["frames", 0, "pose", 3, 0], 0.5)), "frames[0].pose: last row"),
    ("depth key", _edit(lambda d: d["frames"][0].pop("depth")), "frames[0].depth: None"),
    ("absolute path", _edit(_set(["frames", 0, "depth"], "/etc/passwd.png")), "/etc/passwd.png: absolute"),
    ("dot dot", _edit(_set(["frames", 0, "color"], "../x.png")), "../x.png: leaves the bundle"),
    ("extension", _edit(_set(["frames", 0, "features"], "features/000000.txt")), "extension not allowed"),
    ("missing depth file", lambda r: (r / "depth/000001.png").unlink(), "depth/000001.png: missing"),
    ("missing features", lambda r: (r / "features/000000.npy").unlink(), "features/000000.npy: missing"),
    ("symlinked file", _symlink_depth, "depth/000001.png: depth/000001.png is a symbolic link"),
    ("symlinked folder", _symlink_folder, "masks/000000.png: masks is a symbolic link"),
    (
        "depth size",
        _replace_image("depth/000001.png", _SMALL_DEPTH),
        "depth/000001.png: 32x24, expected 64x48",
    ),
    (
        "depth 8 bit",
        _replace_image("depth/000002.png", np.ones((48, 64), np.uint8)),
        "expected 16-bit single",
    ),
    ("truncated depth", _truncate("depth/000000.png"), "depth/000000.png: does not decode"),
    ("truncated jpeg", _truncate("color/000001.jpg", 0.7), "color/000001.jpg: truncated JPEG"),
    ("not an image", lambda r: (r / "masks/000002.png").write_bytes(b"hello"), "masks/000002.png: does not"),
    (
        "gray colour",
        _replace_image("color/000000.jpg", _GRAY),
        "color/000000.jpg: 8-bit 1 channel(s), expected",
    ),
    (
        "rgb masks",
        _replace_image("masks/000000.png", np.zeros((4, 4, 3), np.uint8)),
        "masks/000000.png: 8-bit 3",
    ),
    ("pickled npy", _replace_npy("features/000000.npy", np.array([{}], object), pickle=True), "pickled"),
    (
        "feature dim 4",
        _replace_npy("features/000001.npy", np.zeros((2, 2, 4), np.float32)),
        "last dimension 4",
    ),
    ("features f64", _replace_npy("features/000001.npy", np.zeros((2, 2, DIM))), "dtype float64"),
    (
        "features 2d",
        _replace_npy("features/000001.npy", np.zeros((2, DIM), np.float32)),
        "expected (Hf, Wf, D)",
    ),
    ("fortran", _replace_npy("features/000000.npy", np.zeros((2, 3, DIM), np.float32, order="F")), "Fortran"),
    (
        "features truncated",
        _truncate("features/000000.npy", 0.9),
        "features/000000.npy: shape (6, 8, 8) of float16 declares 768 data bytes, the file holds",
    ),
    ("not npy", lambda r: (r / "features/000001.npy").write_bytes(b"\x93NUMPY junk"), "not a valid .npy"),
    (
        "no features nor colour",
        _edit(lambda d: [_drop_key(k)(d) for k in ("features", "color")]),
        "no frame has feature maps nor a colour image",
    ),
    ("no masks nor colour", _edit(lambda d: [_drop_key(k)(d) for k in ("masks", "color")]), "no frame has masks nor"),
    ("features without header", _edit(lambda d: d.pop("features")), "no features object (dim and space)"),
    (
        "bad geometry",
        lambda r: (r / "geometry.ply").write_bytes(b"ply\nformat ascii 1.0\n"),
        "geometry.ply: ",
    ),
    (
        "vocab kind",
        lambda r: (r / "vocabulary.json").write_text('{"classes": [{"name": "a", "kind": "x"}]}'),
        "kind 'x'",
    ),
    ("vocab json", lambda r: (r / "vocabulary.json").write_text("{"), "vocabulary.json: not valid JSON"),
    (
        "vocab dim",
        _replace_npy("vocabulary.npy", np.ones((3, 5), np.float32)),
        "vocabulary.npy: shape (3, 5)",
    ),
    (
        "vocab nan",
        _replace_npy("vocabulary.npy", np.full((3, DIM), np.nan, np.float32)),
        "vocabulary.npy: contains NaN",
    ),
    (
        "gt range",
        _set_gt(semantic=np.full(NUM_VERTICES, 3), instance=np.zeros(NUM_VERTICES, int)),
        "expected [-1, 3)",
    ),
    ("gt count", _set_gt(semantic=np.zeros(5, int), instance=np.zeros(5, int)), "5 labels, expected 20"),
    (
        "gt float",
        _set_gt(semantic=np.zeros(NUM_VERTICES), instance=np.zeros(NUM_VERTICES, int)),
        "semantic float64",
    ),
    ("gt key", _set_gt(semantic=np.zeros(NUM_VERTICES, int)), "key 'instance' missing"),
    ("gt pickled", _set_gt(semantic=np.array([None] * 3), instance=np.zeros(3, int)), "pickled"),
    ("gt no vocab", lambda r: (r / "vocabulary.json").unlink(), "need vocabulary.json"),
    (
        "deep manifest",
        _edit(_set(["frames", 0, "pose"], _nested(100))),
        "scene.json: nested deeper than the JSON depth limit of 64 levels at frames[0].pose[0][0][0]",
    ),
    (
        "huge integer",
        _raw_manifest_edit('"width": 64', '"width": ' + "6" * 5000),
        "scene.json: an integer of 5,000 digits at camera.width (line",
    ),
    (
        "deep vocabulary",
        lambda r: (r / "vocabulary.json").write_text('{"classes": ' + "[" * 5000 + "]" * 5000 + "}"),
        "vocabulary.json: nested deeper than the JSON depth limit of 64 levels at classes[0][0]",
    ),
    (
        "vocabulary integer",
        lambda r: (r / "vocabulary.json").write_text('{"classes": [{"name": "a", "kind": ' + "1" * 4400 + "}]}"),
        "vocabulary.json: an integer of 4,400 digits at classes[0].kind",
    ),
    ("jpeg named png", _jpeg_as("masks/000000.png"), "masks/000000.png: holds JPEG data, expected PNG"),
    (
        "camera too big",
        _edit(lambda d: d["camera"].update(width=20_000, height=20_000)),
        "scene.json: camera 20000x20000 (400,000,000 pixels), over the pixel limit of 100,000,000",
    ),
    (
        "huge mask",
        lambda r: (r / "masks/000002.png").write_bytes(_declared_png(20_000, 20_000)),
        "masks/000002.png: 20000x20000 (400,000,000 pixels), over the pixel limit of 100,000,000",
    ),
    (
        "depth size by header",
        lambda r: (r / "depth/000000.png").write_bytes(_declared_png(30_000, 3)),
        "depth/000000.png: 30000x3, expected 64x48 (camera)",
    ),
]


@pytest.mark.parametrize(("breaker", "expected"), [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN])
def test_broken_rule_is_reported(bundle_dir: Path, breaker: Callable[[Path], object], expected: str) -> None:
    open_bundle(bundle_dir)  # valid before the change
    breaker(bundle_dir)
    problems = _problems(bundle_dir)
    assert any(expected in p for p in problems), problems


def test_all_problems_reported_at_once(bundle_dir: Path) -> None:
    _edit(_set(["camera", "fx"], 0))(bundle_dir)
    _replace_image("depth/000001.png", _SMALL_DEPTH)(bundle_dir)
    _replace_npy("features/000001.npy", np.zeros((2, 2, 4), np.float32))(bundle_dir)
    (bundle_dir / "masks/000002.png").unlink()
    problems = _problems(bundle_dir)
    expected = [
        "camera.fx 0",
        "depth/000001.png: 32x24",
        "features/000001.npy: last dimension 4",
        "masks/000002.png",
    ]
    for text in expected:
        assert any(text in p for p in problems), (text, problems)
    assert len(problems) == 4, problems


def test_error_message_lists_every_problem(bundle_dir: Path) -> None:
    _edit(_set(["depth_scale"], -1))(bundle_dir)
    _edit(_set(["format"], "x"))(bundle_dir)
    with pytest.raises(BundleError, match="2 problem") as info:
        open_bundle(bundle_dir)
    assert "depth_scale -1" in str(info.value)


def test_not_a_bundle(tmp_path: Path) -> None:
    with pytest.raises(BundleError, match="does not exist"):
        open_bundle(tmp_path / "missing")
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(BundleError, match="not a folder"):
        open_bundle(tmp_path / "file.txt")


class TestWriterFiles:
    def test_add_frame_files_copies_or_links(self, bundle_dir: Path, tmp_path: Path) -> None:
        w = BundleWriter(tmp_path / "copy", name="c", camera=CAM, feature_dim=DIM, feature_space="s")
        for i, link in enumerate((False, True)):
            w.add_frame_files(
                f"f{i}",
                np.eye(4),
                depth=bundle_dir / "depth/000000.png",
                color=bundle_dir / "color/000000.jpg",
                features=bundle_dir / "features/000000.npy",
                masks=bundle_dir / "masks/000000.png",
                link=link,
            )
        scene = open_bundle(w.close())
        assert [f.color for f in scene.frames] == ["color/f0.jpg", "color/f1.jpg"]
        assert (scene.root / "depth/f1.png").read_bytes() == (bundle_dir / "depth/000000.png").read_bytes()
        assert (scene.root / "depth/f0.png").stat().st_nlink == 1  # a copy, never the source itself
        with pytest.raises(InputError, match="expected one of"):
            w.add_frame_files("f9", np.eye(4), depth=bundle_dir / "color/000000.jpg")


class TestWriterExceptions:
    def test_exception(self, tmp_path: Path) -> None:
        w = BundleWriter(tmp_path, name="x", camera=CAM, feature_dim=DIM, feature_space="s")
        depth = np.ones((48, 64))
        with pytest.raises(InputError, match="expected \\(48, 64\\)"):
            w.add_frame("a", np.eye(4), np.ones((10, 10)))
        with pytest.raises(InputError, match="frame id"):
            w.add_frame("../a", np.eye(4), depth)
        with pytest.raises(InputError, match="last dim 3"):
            w.add_frame("a", np.eye(4), depth, features=np.zeros((2, 2, 3), np.float32))
        with pytest.raises(InputError, match="mask ids"):
            w.add_frame("a", np.eye(4), depth, masks=np.full((2, 2), 70000))
        with pytest.raises(InputError, match="pose"):
            w.add_frame("a", np.full((4, 4), np.nan), depth)
        with pytest.raises(InputError, match="at least one frame"):
            w.close()
        w.add_frame("a", np.eye(4), depth)
        with pytest.raises(InputError, match="used twice"):
            w.add_frame("a", np.eye(4), depth)


# -- archives ------------------------------------------------------------------------------------------------


def _zip_folder(folder: Path, out: Path, prefix: str = "") -> Path:
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            zf.write(path, prefix + path.relative_to(folder).as_posix())
    return out


def _zip_entries(out: Path, entries: list[tuple[str | zipfile.ZipInfo, bytes]]) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns about the duplicate names some tests write on purpose
        with zipfile.ZipFile(out, "w") as zf:
            for name, data in entries:
                zf.writestr(name, data)
    return out


def _tar_entries(out: Path, entries: list[tuple[tarfile.TarInfo, bytes]]) -> Path:
    with tarfile.open(out, "w:gz") as tf:
        for info, data in entries:
            info.size = len(data) if info.isreg() else 0
            tf.addfile(info, io.BytesIO(data) if info.isreg() else None)
    return out


def _tar_info(name: str, kind: bytes = tarfile.REGTYPE, link: str = "") -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    info.linkname = link
    return info


class TestArchives:
    def test_zip_round_trip_with_top_folder(self, bundle_dir: Path, tmp_path: Path) -> None:
        archive = _zip_folder(bundle_dir, tmp_path / "scene.zip", prefix="my_scene/")
        scene = open_bundle(archive, workdir=tmp_path / "work")
        assert scene.root.name == "my_scene"
        assert scene.root.is_relative_to(tmp_path / "work")
        assert len(scene.frames) == 3
        assert scene.read_depth(scene.frames[0]).shape == (48, 64)

    def test_tar_gz_round_trip(self, bundle_dir: Path, tmp_path: Path) -> None:
        archive = tmp_path / "scene.tar.gz"
        with tarfile.open(archive, "w:gz") as tf:
            tf.add(bundle_dir, arcname=".")
        scene = open_bundle(archive)
        root = scene.root
        assert (root / "scene.json").is_file()
        assert scene.read_features(scene.frames[1]).shape == (6, 8, DIM)
        del scene  # the temporary extraction goes with the last reference to the scene
        gc.collect()
        assert not root.exists()

    def test_invalid_content_cleans_up(self, bundle_dir: Path, tmp_path: Path) -> None:
        (bundle_dir / "scene.json").unlink()
        archive = _zip_folder(bundle_dir, tmp_path / "scene.zip")
        with pytest.raises(BundleError, match=r"scene\.json: missing"):
            open_bundle(archive, workdir=tmp_path / "work")
        assert list((tmp_path / "work").iterdir()) == []

    @pytest.mark.parametrize(
        ("entries", "expected"),
        [
            ([("../evil.txt", b"x")], "../evil.txt: path leaves the bundle"),
            ([("a/../../evil.txt", b"x")], "path leaves the bundle"),
            ([("/etc/evil.txt", b"x")], "/etc/evil.txt: absolute path"),
            ([("C:/evil.txt", b"x")], "absolute path"),
            ([("a\\..\\evil.txt", b"x")], "backslash"),
            ([("a.txt", b"x"), ("a.txt", b"y")], "a.txt: duplicate name"),
            ([("a", b"x"), ("a/b.txt", b"y")], "'a' is both a file and a folder"),
        ],
    )
    def test_zip_bad_names(self, tmp_path: Path, entries: list[tuple[str, bytes]], expected: str) -> None:
        archive = _zip_entries(tmp_path / "bad.zip", [(n, d) for n, d in entries])
        dest = tmp_path / "out"
        with pytest.raises(BundleError) as info:
            extract_archive(archive, dest)
        assert any(expected in p for p in info.value.problems), info.value.problems
        assert not (tmp_path / "evil.txt").exists()
        assert list(dest.rglob("*")) == []  # nothing written when a member is refused

    def test_zip_symlink(self, tmp_path: Path) -> None:
        link = zipfile.ZipInfo("scene.json")
        link.external_attr = 0o120777 << 16  # S_IFLNK: what `zip --symlinks` stores
        archive = _zip_entries(tmp_path / "l.zip", [(link, b"/etc/passwd")])
        with pytest.raises(BundleError, match=r"scene\.json: symbolic link"):
            extract_archive(archive, tmp_path / "out")

    @pytest.mark.parametrize(
        ("info", "expected"),
        [
            (_tar_info("scene.json", tarfile.SYMTYPE, "/etc/passwd"), "symbolic link to '/etc/passwd'"),
            (_tar_info("x.png", tarfile.LNKTYPE, "../../x"), "hard link"),
            (_tar_info("dev", tarfile.CHRTYPE), "not a regular file"),
            (_tar_info("fifo", tarfile.FIFOTYPE), "not a regular file"),
            (_tar_info("../up.txt"), "leaves the bundle"),
        ],
    )
    def test_tar_unsafe_members(self, tmp_path: Path, info: tarfile.TarInfo, expected: str) -> None:
        archive = _tar_entries(tmp_path / "bad.tar.gz", [(_tar_info("ok.txt"), b"fine"), (info, b"x")])
        with pytest.raises(BundleError) as err:
            open_bundle(archive, workdir=tmp_path / "work")
        assert any(expected in p for p in err.value.problems), err.value.problems
        assert not (tmp_path / "work" / "ok.txt").exists()

    def test_declared_size_bomb(self, tmp_path: Path) -> None:
        # A tar header declaring 1 TB with no data behind it: refused from the header, before any write.
        info = _tar_info("huge.bin")
        info.size = 10**12
        archive = tmp_path / "bomb.tar"
        archive.write_bytes(info.tobuf() + b"\0" * 1024)
        with pytest.raises(BundleError, match="declared uncompressed size 1000000000000"):
            extract_archive(archive, tmp_path / "out", max_bytes=10**9)

    def test_compressed_bomb_over_limit(self, tmp_path: Path) -> None:
        archive = tmp_path / "zeros.zip"
        with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("zeros.bin", b"\0" * 4_000_000)
        assert archive.stat().st_size < 50_000
        with pytest.raises(BundleError, match="exceeds the limit of 1000000"):
            extract_archive(archive, tmp_path / "out", max_bytes=1_000_000)

    def test_lying_declared_size_is_refused(self, tmp_path: Path) -> None:
        # Declared 10 bytes in both headers, 100000 bytes of data: must not expand past what was declared.
        archive = tmp_path / "liar.zip"
        with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as zf:
            zf.writestr("a.bin", b"\x01" * 100_000)
        data = bytearray(archive.read_bytes())
        size = (100_000).to_bytes(4, "little")
        for at in [i for i in range(len(data) - 3) if data[i : i + 4] == size]:
            data[at : at + 4] = (10).to_bytes(4, "little")
        archive.write_bytes(bytes(data))
        dest = tmp_path / "out"
        with pytest.raises(BundleError):
            extract_archive(archive, dest, max_bytes=50_000)
        written = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
        assert written <= 50_000

    def test_too_many_files(self, tmp_path: Path) -> None:
        archive = _zip_entries(tmp_path / "many.zip", [(f"f{i}.txt", b"x") for i in range(10)])
        with pytest.raises(BundleError, match="more than 5 members"):
            extract_archive(archive, tmp_path / "out", max_files=5)

    def test_corrupt_archive(self, bundle_dir: Path, tmp_path: Path) -> None:
        archive = _zip_folder(bundle_dir, tmp_path / "scene.zip")
        data = archive.read_bytes()
        cut = tmp_path / "cut.tar.gz"
        with tarfile.open(cut, "w:gz") as tf:
            tf.add(bundle_dir, arcname=".")
        cut.write_bytes(cut.read_bytes()[:2000])
        with pytest.raises(BundleError, match="corrupt or unreadable"):
            open_bundle(cut)
        (tmp_path / "junk.zip").write_bytes(data[100:])
        with pytest.raises(BundleError):
            open_bundle(tmp_path / "junk.zip")

    def test_corrupt_deflate_data_is_a_bundle_problem(self, tmp_path: Path) -> None:
        archive = tmp_path / "c.zip"
        with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("a.bin", bytes(range(256)) * 400)
        data = bytearray(archive.read_bytes())
        for i in range(60, 200):  # inside the member's compressed bytes: zlib.error, which escaped before
            data[i] ^= 0x5A
        archive.write_bytes(bytes(data))
        with pytest.raises(BundleError, match=r"c\.zip: corrupt or unreadable archive \(Error -3"):
            extract_archive(archive, tmp_path / "out")

    def test_a_host_write_error_is_not_the_bundles(
        self, bundle_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        # A full disk is the host's problem: it passes on as OSError (the service keeps the upload for a retry)
        # instead of a 422 "corrupt archive"; a name the file system refuses is the bundle's, named relatively.
        archive = _zip_folder(bundle_dir, tmp_path / "scene.zip")
        real_open = Path.open

        def failing_open(self: Path, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
            if mode == "xb" and self.name == "scene.json":
                raise OSError(fail_with, os.strerror(fail_with), str(self))
            return real_open(self, mode, *args, **kwargs)

        monkeypatch.setattr(Path, "open", failing_open)
        fail_with = errno.ENOSPC
        with pytest.raises(OSError) as info:
            extract_archive(archive, tmp_path / "out1")
        assert not isinstance(info.value, BundleError)
        assert info.value.errno == errno.ENOSPC
        fail_with = errno.ENAMETOOLONG
        with pytest.raises(BundleError) as bundle_info:
            extract_archive(archive, tmp_path / "out2")
        assert bundle_info.value.problems == ["scene.json: cannot be extracted under this name (File name too long)"]

    def test_format_id_exported(self) -> None:
        assert FORMAT_ID == "panogs-scene/1"


# -- limits (hostile input) ----------------------------------------------------------------------------------


def test_images_over_a_limit_are_refused_without_being_read(bundle_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (bundle_dir / "masks/000000.png").write_bytes(_declared_png(20_000, 20_000))
    (bundle_dir / "depth/000001.png").write_bytes(_declared_png(640, 480))
    read: list[str] = []
    real_check = panogs_core.io.bundle.file_checks.data_problem

    def recording_check(root: Path, rel: str) -> str | None:
        read.append(rel)
        return real_check(root, rel)

    monkeypatch.setattr(panogs_core.io.bundle.file_checks, "data_problem", recording_check)
    problems = _problems(bundle_dir)
    assert "masks/000000.png: 20000x20000 (400,000,000 pixels), over the pixel limit of 100,000,000" in problems
    assert "depth/000001.png: 640x480, expected 64x48 (camera)" in problems
    assert "masks/000000.png" not in read
    assert "depth/000001.png" not in read
    assert "depth/000000.png" in read  # the others' data is still checked (a truncated file shows only then)


def test_validation_decodes_no_image_and_finds_altered_png_data(
    bundle_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    data = bytearray((bundle_dir / "depth/000002.png").read_bytes())
    data[-20] ^= 0xFF  # a byte of the last IDAT's data: the file is whole, its chunk's CRC no longer matches
    (bundle_dir / "depth/000002.png").write_bytes(bytes(data))
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("validation decoded an image"))
    monkeypatch.setattr(cv2, "imread", lambda *a: pytest.fail("validation decoded an image"))
    problems = _problems(bundle_dir)
    assert problems == ["depth/000002.png: does not decode as an image (corrupt PNG: the CRC of its 'IDAT' chunk does "
                        "not match)"]  # fmt: skip


def test_limits_are_parameters(bundle_dir: Path) -> None:
    with pytest.raises(BundleError) as info:
        open_bundle(bundle_dir, limits=BundleLimits(max_image_pixels=1_000))
    assert "scene.json: camera 64x48 (3,072 pixels), over the pixel limit of 1,000" in info.value.problems
    assert "depth/000000.png: 64x48 (3,072 pixels), over the pixel limit of 1,000" in info.value.problems
    assert "features/000000.npy: 8x6 cells (48), over the pixel limit of 1,000" not in info.value.problems
    with pytest.raises(BundleError) as info:
        open_bundle(bundle_dir, limits=BundleLimits(json=JsonLimits(max_depth=4)))
    assert any(
        p.startswith("scene.json: nested deeper than the JSON depth limit of 4 levels at frames[0].pose[0]")
        for p in info.value.problems
    ), info.value.problems
    size = (bundle_dir / "scene.json").stat().st_size
    with pytest.raises(BundleError) as info:
        open_bundle(bundle_dir, limits=BundleLimits(json=JsonLimits(max_bytes=1_000)))
    assert f"scene.json: {size:,} bytes, over the JSON size limit of 1,000 bytes" in info.value.problems
    assert open_bundle(bundle_dir, limits=BundleLimits(json=JsonLimits(max_depth=5))).name == "tiny"


def test_long_member_name_is_refused_without_the_storage_path(bundle_dir: Path, tmp_path: Path) -> None:
    archive = _zip_folder(bundle_dir, tmp_path / "scene.zip")
    with zipfile.ZipFile(archive, "a") as zf:
        zf.writestr("masks/" + "m" * 300 + ".png", b"x")
        zf.writestr("deep/" * 300 + "x.txt", b"x")
    work = tmp_path / "work"
    with pytest.raises(BundleError) as info:
        open_bundle(archive, workdir=work)
    message = str(info.value)
    assert str(tmp_path) not in message
    assert "masks/mmmm" in message
    assert "(310 characters): a part of the name is 304 bytes long, over the limit of 255" in message
    assert "name over the limit of 1,024 bytes" in message
    assert list(work.iterdir()) == []


def test_no_problem_names_where_the_bundle_lies(bundle_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A library's message that carries the absolute file name (an OSError's does) is cut to the relative path.
    def failing_header(path: Path, *, name: str | None = None) -> None:
        raise InputError(f"{name}: cannot be read ({path}: input/output error)")

    monkeypatch.setattr(panogs_core.io.bundle.file_checks, "read_image_header", failing_header)
    problems = _problems(bundle_dir)
    assert "depth/000000.png: cannot be read (depth/000000.png: input/output error)" in problems
    assert not any(str(bundle_dir) in p or str(bundle_dir.resolve()) in p for p in problems)


def test_synthetic_bundle_fits_the_default_limits(bundle_dir: Path) -> None:
    # The service's defaults (docs/service.md, Limits) are far above what a real manifest needs.
    assert (bundle_dir / "scene.json").stat().st_size < 16 * 1024**2
    scene = open_bundle(
        bundle_dir, limits=BundleLimits(json=JsonLimits(max_bytes=16 * 1024**2), max_image_pixels=40_000_000)
    )
    assert len(scene.frames) == 3


# -- binary headers: .npy shapes and .npz members are bounded before anything is allocated ----------------------


def _raw_npy(shape: str, descr: str = "<f4", data: bytes = b"") -> bytes:
    """A version 1.0 .npy whose header says ``shape`` (any text: np.save cannot write a false shape)."""
    text = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape)  # noqa: UP031
    header = text.encode("latin1") + b" " * ((64 - (10 + len(text) + 1) % 64) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + data


def _write(rel: str, data: bytes) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        (root / rel).write_bytes(data)

    return apply


def _gt_zip(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        with zipfile.ZipFile(root / "gt" / "labels.npz", "w", method) as zf:
            for name, data in members.items():
                zf.writestr(name, data)

    return apply


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


_F = "features/000000.npy"
_LABELS = _npy(np.zeros(NUM_VERTICES, np.int64))
BINARY_HEADERS = [
    (
        "size past int64",  # the brief's case: np.prod in int64 wrapped it, an empty file passed as complete
        _write(_F, _raw_npy(f"({10**19}, 6, {DIM})")),
        f"{_F}: shape (10000000000000000000, 6, {DIM}), expected at most 32 integer sizes in [0, 2**63)",
    ),
    (
        "size past any int",  # np.prod raised OverflowError: a 500 at the API
        _write(_F, _raw_npy(f"({10**30}, 6, {DIM})")),
        f"{_F}: shape ({10**30}, 6, {DIM}), expected at most 32 integer sizes in [0, 2**63)",
    ),
    (
        "product past int64",  # each size fits, the product does not: exact integers, never wrapped
        _write(_F, _raw_npy(f"({10**18}, 6, {DIM})")),
        f"{_F}: shape (1000000000000000000, 6, {DIM}) of float32 declares 192,000,000,000,000,000,000 data "
        "bytes, the file holds 0 after its header",
    ),
    (
        "cells times dim wraps",  # 4 cells x 2**62 is 0 in int64: within the pixel limit, and passed as complete
        lambda r: (
            _edit(_set(["features", "dim"], 2**62))(r),
            _write(_F, _raw_npy(f"(4, 1, {2**62})"))(r),
        ),
        f"{_F}: shape (4, 1, {2**62}) of float32 declares {2**66:,} data bytes, the file holds 0 after its header",
    ),
    (
        "wraps to the data size",  # (2**61 + 1) * 32 bytes is 32 modulo 2**64: the 32 bytes present matched
        _write(_F, _raw_npy(f"({2**61 + 1}, 1, {DIM})", data=bytes(32))),
        f"{_F}: shape ({2**61 + 1}, 1, {DIM}) of float32 declares {(2**61 + 1) * 32:,} data bytes, the file holds 32",
    ),
    ("negative size", _write(_F, _raw_npy(f"(-5, 6, {DIM})")), f"{_F}: shape (-5, 6, {DIM}), expected at most 32"),
    ("bool size", _write(_F, _raw_npy(f"(True, 6, {DIM})")), f"{_F}: shape (True, 6, {DIM}), expected at most 32"),
    ("size over intp", _write(_F, _raw_npy(f"({2**70}, 0, {DIM})")), f"{_F}: shape ({2**70}, 0, {DIM}), expected"),
    ("too many dims", _write(_F, _raw_npy("(1,) * 40")), f"{_F}: not a valid .npy file"),
    (
        "vocabulary past int64",
        _write("vocabulary.npy", _raw_npy(f"(3, {2**62 + DIM})", data=bytes(3 * DIM * 4))),
        f"vocabulary.npy: shape (3, {2**62 + DIM}) of float32 declares {3 * (2**62 + DIM) * 4:,} data bytes",
    ),
    (
        "gt member past int64",  # passed the old int64 check by wrapping, then np.load failed to allocate
        _gt_zip({"semantic.npy": _raw_npy(f"({2**61 + 1},)", "<i8", bytes(8)), "instance.npy": _LABELS}),
        f"gt/labels.npz: semantic.npy: shape ({2**61 + 1},) of int64 declares {(2**61 + 1) * 8:,} data bytes, "
        "the file holds 8",
    ),
    (
        "gt member shorter than its header",
        _gt_zip({"semantic.npy": _raw_npy("(1000000000,)", "<i8"), "instance.npy": _LABELS}),
        "gt/labels.npz: semantic.npy: shape (1000000000,) of int64 declares 8,000,000,000 data bytes, the file holds 0",
    ),
    (
        "gt pickled member",
        _gt_zip({"semantic.npy": _raw_npy("(3,)", "|O"), "instance.npy": _LABELS}),
        "gt/labels.npz: semantic.npy: holds pickled Python objects",
    ),
    (
        "gt member twice",
        _gt_zip({"semantic.npy": _LABELS, "instance.npy": _LABELS, "semantic": _LABELS}),
        "gt/labels.npz: member 'semantic' appears twice",
    ),
    (
        "gt not npy",
        _gt_zip({"semantic.npy": b"hello", "instance.npy": _LABELS}),
        "gt/labels.npz: semantic.npy: not a valid .npy file",
    ),
    (
        "geometry count of 5000 digits",  # int() refused it with a ValueError: a 500 at the API
        _write("geometry.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex " + b"9" * 5000 + b"\n"),
        "geometry.ply: line 3: PLY element 'vertex' count of 5,000 digits, expected at most 19",
    ),
    (
        "geometry count past the file",
        _write(
            "geometry.ply",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 9223372036854775807\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n" + bytes(12),
        ),
        "geometry.ply: PLY element 'vertex' truncated or its count false: 9,223,372,036,854,775,807 rows need at "
        "least 110,680,464,442,257,309,684 bytes of data, the file holds 12 after its header",
    ),
]


@pytest.mark.parametrize(("breaker", "expected"), [b[1:] for b in BINARY_HEADERS], ids=[b[0] for b in BINARY_HEADERS])
def test_binary_header_is_bounded(bundle_dir: Path, breaker: Callable[[Path], object], expected: str) -> None:
    breaker(bundle_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zipfile warns about the duplicate member name
        problems = _problems(bundle_dir)
    assert any(p.startswith(expected) for p in problems), problems


def test_gt_unread_members_are_ignored(bundle_dir: Path) -> None:
    # A member that is not one of the documented keys is never decompressed, whatever its header says.
    scene_gt = np.load(bundle_dir / "gt" / "labels.npz")
    members = {f"{k}.npy": _npy(scene_gt[k]) for k in scene_gt.files}
    _gt_zip({**members, "junk.npy": _raw_npy(f"({10**30},)")})(bundle_dir)
    assert open_bundle(bundle_dir).read_ground_truth() is not None


def test_gt_zip_bomb_is_refused_by_declared_sizes(bundle_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # 64 MiB of zeros deflate to about 64 KB; the declared sizes alone are over a 32 MiB limit, so nothing is
    # decompressed past the headers.
    count = 8 * 1024**2
    bomb = np.lib.format.header_data_from_array_1_0(np.zeros(1, np.int64))
    bomb["shape"] = (count,)
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, bomb)
    path = bundle_dir / "gt" / "labels.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("semantic.npy", "w", force_zip64=True) as fh:
            fh.write(buffer.getvalue())
            for _ in range(count // 2**20):
                fh.write(bytes(8 * 2**20))
        zf.writestr("instance.npy", _npy(np.zeros(count, np.int64)))
    assert path.stat().st_size < 1_000_000

    read_array = np.lib.format.read_array

    def no_member_read(fh: Any, *args: Any, **kwargs: Any) -> np.ndarray:
        assert not isinstance(fh, zipfile.ZipExtFile), "an array of the .npz was decompressed"
        return read_array(fh, *args, **kwargs)

    monkeypatch.setattr(np.lib.format, "read_array", no_member_read)
    with pytest.raises(BundleError) as info:
        open_bundle(bundle_dir, limits=BundleLimits(max_ground_truth_bytes=32 * 1024**2))
    expected = (
        f"gt/labels.npz: arrays expand to {2 * (8 * count + 128):,} bytes, over the ground-truth limit of "
        "33,554,432 bytes"
    )
    assert expected in info.value.problems, info.value.problems


@pytest.mark.parametrize(
    ("patch", "expected"),
    [
        (lambda flag, method: (flag, 99), "not a valid .npz file (That compression method is not supported)"),
        (lambda flag, method: (flag | 1, method), "not a valid .npz file"),  # the 'encrypted' flag
    ],
    ids=["unknown compression", "encrypted"],
)
def test_gt_member_zipfile_cannot_read(
    bundle_dir: Path, patch: Callable[[int, int], tuple[int, int]], expected: str
) -> None:
    # Both raised past the old handler (NotImplementedError, RuntimeError): a 500 at the API.
    path = bundle_dir / "gt" / "labels.npz"
    data = bytearray(path.read_bytes())
    for signature, at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):  # local headers; central directory entries
        start = data.find(signature)
        while start != -1:
            flag, method = struct.unpack_from("<HH", data, start + at)
            struct.pack_into("<HH", data, start + at, *patch(flag, method))
            start = data.find(signature, start + 4)
    path.write_bytes(bytes(data))
    problems = _problems(bundle_dir)
    assert any(p.startswith("gt/labels.npz: " + expected) for p in problems), problems


def test_gt_limit_counts_every_read_member(bundle_dir: Path) -> None:
    # The tiny bundle's labels: two members of 20 int64 and a 128-byte header each, 576 bytes in all.
    assert open_bundle(bundle_dir, limits=BundleLimits(max_ground_truth_bytes=576)).has_ground_truth
    with pytest.raises(BundleError, match=r"gt/labels\.npz: arrays expand to 576 bytes, over the ground-truth limit"):
        open_bundle(bundle_dir, limits=BundleLimits(max_ground_truth_bytes=575))


class TestValidationBudgets:
    """Each file kind is bounded by what a scene needs, and each check's work by the file's size."""

    def test_too_many_classes_refused_by_count(self, bundle_dir: Path) -> None:
        classes = [{"name": f"class {i}", "kind": "thing"} for i in range(20_000)]
        (bundle_dir / "vocabulary.json").write_text(json.dumps({"classes": classes}))
        assert "vocabulary.json: 20,000 classes, over the limit of 4,096" in _problems(bundle_dir)

    def test_repeated_name_found_among_many(self, bundle_dir: Path) -> None:
        classes = [{"name": f"class {i}", "kind": "thing"} for i in range(4_000)] + [{"name": "class 0", "kind": "x"}]
        (bundle_dir / "vocabulary.json").write_text(json.dumps({"classes": classes}))
        problems = _problems(bundle_dir)
        assert "vocabulary.json: classes[4000].name 'class 0' repeated, expected unique names" in problems

    def test_feature_dim_has_a_maximum(self, bundle_dir: Path) -> None:
        _edit(_set(["features", "dim"], 1_000_000))(bundle_dir)
        problems = _problems(bundle_dir)
        assert "scene.json: features.dim 1,000,000, over the limit of 2,048" in problems
        # The embeddings' width is not read without a valid dim (a 256 MiB vocabulary.npy cost the API 1 GB).
        assert not any(p.startswith("vocabulary.npy") for p in problems)

    def test_png_of_empty_chunks_refused_by_count(self, bundle_dir: Path) -> None:
        rel = _manifest(bundle_dir)["frames"][0]["depth"]
        data = (bundle_dir / rel).read_bytes()
        empty = struct.pack(">I", 0) + b"zzZz" + struct.pack(">I", zlib.crc32(b"zzZz"))
        ihdr_end = 8 + 12 + 13  # signature, then IHDR's length, type, 13 data bytes and CRC
        (bundle_dir / rel).write_bytes(data[:ihdr_end] + empty * 100_000 + data[ihdr_end:])
        problems = _problems(bundle_dir)
        assert any(p.startswith(f"{rel}: does not decode as an image (more than ") and "chunks" in p for p in problems)

    def test_a_file_shared_by_frames_is_checked_once(self, bundle_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        doc = _manifest(bundle_dir)
        for frame in doc["frames"]:
            frame["depth"] = doc["frames"][0]["depth"]
        _save(bundle_dir, doc)
        calls: list[int] = []
        walk = panogs_core.io.bundle.file_checks.png_framing_problem

        def counted(data: bytes, max_chunks: int) -> str | None:
            calls.append(len(data))
            return walk(data, max_chunks)

        monkeypatch.setattr(panogs_core.io.bundle.file_checks, "png_framing_problem", counted)
        open_bundle(bundle_dir)
        pngs = {f[k] for f in doc["frames"] for k in ("depth", "masks", "color") if f.get(k, "").endswith(".png")}
        assert len(calls) == len(pngs)


@pytest.mark.parametrize("drop", [("features",), ("masks",), ("features", "masks")])
def test_a_bundle_without_maps_validates_when_its_frames_have_colour(bundle_dir: Path, drop: tuple[str, ...]) -> None:
    doc = _manifest(bundle_dir)
    for key in drop:
        for frame in doc["frames"]:
            frame.pop(key, None)
    if "features" in drop:
        doc.pop("features")
        (bundle_dir / "vocabulary.json").unlink(missing_ok=True)
        (bundle_dir / "vocabulary.npy").unlink(missing_ok=True)
        (bundle_dir / "gt" / "labels.npz").unlink(missing_ok=True)
    _save(bundle_dir, doc)
    bundle = open_bundle(bundle_dir)
    assert not bundle.feature_frames if "features" in drop else bundle.feature_frames
    assert not bundle.mask_frames if "masks" in drop else bundle.mask_frames
    assert (bundle.feature_dim == 0 and bundle.feature_space == "") is ("features" in drop)
