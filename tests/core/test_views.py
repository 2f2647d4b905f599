"""Renders of a run: `panogs render` by frame or pose, labels by the top-weight Gaussian, a query's relevance."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from gaussian_runs import opaque_gaussians
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture)

from panogs_core.cli import main as cli_main
from panogs_core.errors import InputError
from panogs_core.gaussians.ply import write_gaussian_ply
from panogs_core.gaussians.views import (
    load_run_scene,
    parse_size,
    render_to_dir,
    render_view,
    view_from_frame,
    view_from_pose,
    write_cameras,
)
from panogs_core.stages.export import write_vocabulary
from panogs_core.types import Camera, Frame, Vocabulary

CAMERA = Camera(width=40, height=30, fx=30.0, fy=30.0, cx=19.5, cy=14.5)
RED, BLUE = (0.9, 0.1, 0.1), (0.1, 0.1, 0.9)


def _grid(x0: float, x1: float, z: float, step: float = 0.03) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(-0.7, 0.7, step))
    return np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1).astype(np.float32)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A blue wall (class 0, stuff) at z = 2 with a red chair (class 1, instance 0) in front of its left half."""
    out = tmp_path_factory.mktemp("run")
    wall, chair = _grid(-1.2, 1.2, 2.0), _grid(-1.2, -0.1, 1.0, step=0.02)
    means = np.concatenate([wall, chair])
    n = len(means)
    colors = np.array([BLUE] * len(wall) + [RED] * len(chair), np.float32)
    scene = opaque_gaussians(means, colors, 0.03)
    semantic = np.array([0] * len(wall) + [1] * len(chair))
    instance = np.array([-1] * len(wall) + [0] * len(chair))
    write_gaussian_ply(out / "gaussians.ply", scene, np.zeros((n, 3), np.float32), semantic, instance)
    write_cameras(out / "cameras.json", CAMERA, [Frame(id="f0", T_world_cam=np.eye(4), depth="d.png")])
    emb = np.eye(2, 4, dtype=np.float32)
    write_vocabulary(out, Vocabulary(names=("wall", "chair"), kinds=("stuff", "thing"), embeddings=emb), "test-space")
    inst = {"id": 0, "class_index": 1, "class_name": "chair", "kind": "thing", "score": 0.9, "num_points": 10}
    inst |= {"centroid": [-0.6, 0, 1], "bbox_min": [-1.2, -0.7, 1], "bbox_max": [-0.1, 0.7, 1]}
    (out / "instances.json").write_text(json.dumps([inst]))
    np.save(out / "instance_features.npy", emb[1:2])
    return out


def test_labels_colour_and_depth_of_a_key_frame(run_dir: Path) -> None:
    view = view_from_frame(run_dir, "f0", None)
    img = render_view(load_run_scene(run_dir), view)
    left, right = (15, 8), (15, 32)  # (row, col): the chair covers the left half of the image
    assert img.semantic[left] == 1
    assert img.instance[left] == 0
    assert img.semantic[right] == 0
    assert img.instance[right] == -1
    assert img.depth[left] == pytest.approx(1.0, abs=0.01)
    assert img.depth[right] == pytest.approx(2.0, abs=0.01)
    assert img.color[left][0] > 200  # red
    assert img.color[right][2] > 200  # blue


def test_cli_writes_every_png_and_the_query_relevance(run_dir: Path, tmp_path: Path) -> None:
    code = cli_main(
        ["render", str(run_dir), "--frame", "f0", "--size", "80x60", "--query", "chair", "--out", str(tmp_path)]
    )
    assert code == 0
    names = {"color.png", "depth.png", "depth_vis.png", "semantic.png", "instance.png", "panoptic.png", "relevance.png"}
    assert {p.name for p in tmp_path.iterdir()} == names
    depth = cv2.imread(str(tmp_path / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.shape == (60, 80)
    assert depth.dtype == np.uint16
    assert abs(int(depth[30, 70]) - 2000) <= 20  # millimetres, the wall
    heat = cv2.imread(str(tmp_path / "relevance.png"))[..., ::-1]  # JET: hot red on the chair, blue elsewhere
    assert heat[30, 10, 0] > heat[30, 10, 2]
    assert heat[30, 70, 2] > heat[30, 70, 0]


def test_a_pose_file_with_its_own_camera(run_dir: Path, tmp_path: Path) -> None:
    pose = np.eye(4)
    pose[0, 3] = -0.6  # step left: the chair now fills the centre
    cam = {"width": 20, "height": 10, "fx": 15.0, "fy": 15.0, "cx": 9.5, "cy": 4.5}
    doc = {"T_world_cam": pose.tolist(), "camera": cam}
    (tmp_path / "pose.json").write_text(json.dumps(doc))
    out = tmp_path / "out"
    assert cli_main(["render", str(run_dir), "--pose", str(tmp_path / "pose.json"), "--out", str(out)]) == 0
    sem = cv2.imread(str(out / "semantic.png"))
    assert sem.shape == (10, 20, 3)
    img = render_view(load_run_scene(run_dir), view_from_pose(doc, CAMERA, None, "pose"))
    assert img.semantic[5, 10] == 1


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ({"pose": []}, "expected an object with 'T_world_cam'"),
        ({"T_world_cam": [[1, 0], [0, 1]]}, "expected a finite 4x4 matrix"),
        ({"T_world_cam": (2 * np.eye(4)).tolist()}, "not a rigid transform"),
        ({"T_world_cam": np.eye(4).tolist(), "camera": {"width": 0}}, r"camera.width: expected an integer >= 1"),
        ({"T_world_cam": np.eye(4).tolist(), "extra": 1}, "unknown key"),
    ],
)
def test_bad_poses_are_refused_with_the_field(doc: dict, match: str) -> None:
    with pytest.raises(InputError, match=match):
        view_from_pose(doc, CAMERA, None, "pose")


def test_bad_frame_size_and_missing_run(run_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such frame"):
        render_to_dir(run_dir, tmp_path, frame="nope")
    with pytest.raises(InputError, match="WIDTHxHEIGHT"):
        parse_size("640by480")
    with pytest.raises(InputError, match="at most"):
        view_from_frame(run_dir, "f0", (20000, 20000))
    assert cli_main(["render", str(tmp_path / "none"), "--frame", "f0", "--out", str(tmp_path / "o")]) == 2
