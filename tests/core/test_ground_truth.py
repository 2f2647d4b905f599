"""Ground truth on import (``--gt``) and on evaluation (``panogs eval RUN --gt``): .npz and ScanNet annotations.

The ScanNet fixture is a 10-vertex labelled mesh with its aggregation and segments files, written with known
answers: NYU40 ids map to ScanNet-20 indices, each segGroup is one instance, wall / floor and vertices in no
group get instance -1.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from panogs_core.cli import main as cli_main
from panogs_core.errors import InputError
from panogs_core.evaluation.metrics import evaluate
from panogs_core.io.bundle import open_bundle
from panogs_core.io.ground_truth import (
    SCANNET20_NYU40_IDS,
    load_ground_truth,
    nyu40_to_scannet20,
    read_scannet_ground_truth,
)
from panogs_core.io.importers.scannet import import_scannet
from panogs_core.io.ply import write_ply
from panogs_core.language.label_sets import builtin_vocabulary
from panogs_core.stages.export import write_vocabulary
from panogs_core.types import Vocabulary

D = 512  # the built-in ScanNet-20 embeddings are 512-d
SCENE = "scene0000_00"
# Per vertex: NYU40 label, over-segment id. Groups below: wall 0, floor 1, two chairs 2 and 3, ceiling 4
# (NYU40 22, not in ScanNet-20), otherfurniture 5, desk 7; segment 500 is in no group.
NYU40 = [1, 1, 2, 5, 5, 5, 22, 0, 39, 14]
SEGMENTS = [100, 100, 200, 300, 300, 301, 400, 500, 600, 700]
GROUPS = [(0, "wall", [100]), (1, "floor", [200]), (2, "chair", [300]), (3, "chair", [301]), (4, "ceiling", [400]),
          (5, "cabinet stand", [600]), (7, "desk", [700, 9999])]  # fmt: skip
EXPECTED_SEMANTIC = [0, 0, 1, 4, 4, 4, -1, -1, 19, 12]
EXPECTED_INSTANCE = [-1, -1, -1, 2, 2, 3, 4, -1, 5, 7]


def _mesh_points() -> np.ndarray:  # (10, 3) float32
    return np.random.default_rng(3).uniform(0, 3, (len(NYU40), 3)).astype(np.float32)


def _scannet_annotations(folder: Path, *, segments: list[int] | None = None) -> Path:
    """``<scene>_vh_clean_2.labels.ply`` + aggregation + segs in ``folder``; returns the labels PLY."""
    folder.mkdir(parents=True, exist_ok=True)
    pts = _mesh_points()
    colour = np.full(len(pts), 200, np.uint8)
    fields = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "red": colour, "green": colour, "blue": colour}
    fields["alpha"] = np.full(len(pts), 255, np.uint8)
    fields["label"] = np.asarray(NYU40, np.uint16)
    labels_ply = write_ply(folder / f"{SCENE}_vh_clean_2.labels.ply", fields, faces=np.array([[0, 1, 2], [3, 4, 5]]))
    seg_groups = [
        {"id": obj, "objectId": obj, "label": label, "segments": segs} for obj, label, segs in GROUPS
    ]  # fmt: skip
    aggregation = {"sceneId": f"scannet.{SCENE}", "segGroups": seg_groups,
                   "segmentsFile": f"scannet.{SCENE}_vh_clean_2.0.010000.segs.json"}  # fmt: skip
    (folder / f"{SCENE}.aggregation.json").write_text(json.dumps(aggregation))
    segs = {"sceneId": SCENE, "segIndices": SEGMENTS if segments is None else segments}
    (folder / f"{SCENE}_vh_clean_2.0.010000.segs.json").write_text(json.dumps(segs))
    return labels_ply


def _mesh(path: Path) -> Path:
    """The scene mesh (``_vh_clean_2.ply``): the labelled mesh's vertices without labels."""
    pts = _mesh_points()
    return write_ply(path, {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, faces=np.array([[0, 1, 2]]))


def _scan(root: Path, n: int = 3) -> Path:
    """A minimal ScanNet export: n frames of 16x12 depth with 512-d feature maps and masks."""
    rng = np.random.default_rng(0)
    for sub in ("depth", "pose", "intrinsic", "features", "masks"):
        (root / sub).mkdir(parents=True)
    np.savetxt(
        root / "intrinsic" / "intrinsic_depth.txt", [[14.0, 0, 7.5, 0], [0, 14, 5.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    )
    for i in range(n):
        assert cv2.imwrite(str(root / "depth" / f"{i}.png"), rng.integers(500, 3000, (12, 16)).astype(np.uint16))
        np.savetxt(root / "pose" / f"{i}.txt", np.eye(4))
        np.save(root / "features" / f"{i}.npy", rng.normal(size=(3, 4, D)).astype(np.float16))
        assert cv2.imwrite(str(root / "masks" / f"{i}.png"), rng.integers(0, 4, (12, 16)).astype(np.uint8))
    return root


def _npz(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)
    return path


def _vocab(names: tuple[str, ...] = ("wall", "chair", "table")) -> Vocabulary:
    kinds = tuple("stuff" if n == "wall" else "thing" for n in names)
    return Vocabulary(names, kinds, np.eye(len(names), D, dtype=np.float32))


class TestScanNetAnnotations:
    def test_nyu40_mapping(self) -> None:
        np.testing.assert_array_equal(nyu40_to_scannet20(np.array(SCANNET20_NYU40_IDS)), np.arange(20))
        np.testing.assert_array_equal(nyu40_to_scannet20(np.array([0, 13, 15, 40, 41, 65535])), -1)

    def test_known_answers(self, tmp_path: Path) -> None:
        gt = read_scannet_ground_truth(_scannet_annotations(tmp_path))
        np.testing.assert_array_equal(gt.semantic, EXPECTED_SEMANTIC)
        np.testing.assert_array_equal(gt.instance, EXPECTED_INSTANCE)
        assert gt.points is not None
        np.testing.assert_array_equal(gt.points, _mesh_points())

    def test_exception(self, tmp_path: Path) -> None:
        labels_ply = _scannet_annotations(tmp_path / "a", segments=SEGMENTS[:-1])
        with pytest.raises(InputError, match=r"segs\.json: segIndices has 9 entries, expected 10"):
            read_scannet_ground_truth(labels_ply)
        labels_ply = _scannet_annotations(tmp_path / "b")
        (tmp_path / "b" / f"{SCENE}.aggregation.json").unlink()
        with pytest.raises(InputError, match=rf"{SCENE}\.aggregation\.json"):
            read_scannet_ground_truth(labels_ply)
        renamed = labels_ply.rename(tmp_path / "b" / "labels.ply")
        with pytest.raises(InputError, match=r"_vh_clean_2\.labels\.ply"):
            read_scannet_ground_truth(renamed)
        labels_ply = _scannet_annotations(tmp_path / "c")
        bad = {"segGroups": [{"objectId": "x", "segments": [1]}]}
        (tmp_path / "c" / f"{SCENE}.aggregation.json").write_text(json.dumps(bad))
        with pytest.raises(InputError, match=r"segGroups\[0\]\.objectId 'x'"):
            read_scannet_ground_truth(labels_ply)
        (tmp_path / "c" / f"{SCENE}.aggregation.json").write_text(json.dumps({"sceneId": SCENE}))
        with pytest.raises(InputError, match=r"aggregation\.json: segGroups missing"):
            read_scannet_ground_truth(labels_ply)
        pts = _mesh_points()
        write_ply(labels_ply, {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]})
        with pytest.raises(InputError, match="vertex property 'label' missing"):
            read_scannet_ground_truth(labels_ply)


class TestLoadNpz:
    def test_points_and_per_vertex(self, tmp_path: Path) -> None:
        pts = _mesh_points()
        sem, ins = np.array([0, 1, 1, 2, -1, 0, 0, 1, 2, 2]), np.array([-1, 0, 0, 1, -1, -1, -1, 2, 3, 3])
        gt = load_ground_truth(_npz(tmp_path / "p.npz", semantic=sem, instance=ins, points=pts), _vocab())
        assert gt.points is not None
        assert gt.semantic.dtype == gt.instance.dtype == np.int64
        # Points exactly on the vertices: labels become per vertex.
        gt = load_ground_truth(tmp_path / "p.npz", _vocab(), vertices=pts)
        assert gt.points is None
        # The reference's float64 labels (with -0.0) are accepted.
        path = _npz(tmp_path / "f.npz", semantic=sem.astype(np.float64) * 1.0 - 0.0, instance=ins.astype(np.float64))
        gt = load_ground_truth(path, _vocab(), vertices=pts)
        np.testing.assert_array_equal(gt.semantic, sem)

    @pytest.mark.parametrize(
        ("arrays", "vertices", "match"),
        [
            ({"semantic": np.zeros(3, np.int64)}, None, "key 'instance' missing"),
            ({"semantic": np.zeros(3), "instance": np.zeros(2)}, None, "instance has 2 values, expected 3"),
            ({"semantic": np.array([0, 3, 1]), "instance": np.zeros(3)}, None,
             r"semantic in \[0, 3\], expected \[-1, 3\)"),
            ({"semantic": np.array([0.5, 1, 1]), "instance": np.zeros(3)}, None, "semantic has non-integer value 0.5"),
            ({"semantic": np.zeros((3, 1)), "instance": np.zeros(3)}, None, r"semantic float64 \(3, 1\)"),
            ({"semantic": np.zeros(3), "instance": np.array([0, -2, 1])}, None, "instance has minimum -2"),
            ({"semantic": np.zeros(3), "instance": np.zeros(3), "points": np.zeros((3, 2))}, None,
             r"points float64 \(3, 2\)"),
            ({"semantic": np.zeros(3), "instance": np.zeros(3)}, None, "points: missing"),
            ({"semantic": np.zeros(3), "instance": np.zeros(3)}, np.zeros((4, 3)),
             r"semantic: 3 labels .* \(4 vertices\)"),
        ],
    )  # fmt: skip
    def test_exception(
        self, tmp_path: Path, arrays: dict[str, np.ndarray], vertices: np.ndarray | None, match: str
    ) -> None:
        path = _npz(tmp_path / "gt.npz", **arrays)
        with pytest.raises(InputError, match=rf"gt\.npz: {match}"):
            load_ground_truth(path, _vocab(), vertices=vertices)

    def test_unknown_kind_and_missing_file(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match="does not exist"):
            load_ground_truth(tmp_path / "none.npz", _vocab())
        (tmp_path / "gt.txt").write_text("1 2 3")
        with pytest.raises(InputError, match=r"unknown ground truth kind '\.txt'"):
            load_ground_truth(tmp_path / "gt.txt", _vocab())


class TestImportWithGroundTruth:
    def test_scannet_annotations_without_geometry_keep_points(self, tmp_path: Path) -> None:
        labels_ply = _scannet_annotations(tmp_path / "ann")
        report = import_scannet(_scan(tmp_path / SCENE), tmp_path / "b", ground_truth=labels_ply)
        scene = open_bundle(report.bundle)
        assert scene.vocabulary is not None
        assert scene.vocabulary.names == builtin_vocabulary("scannet20").names  # brought by the annotations
        gt = scene.read_ground_truth()
        assert gt is not None
        assert gt.points is not None
        np.testing.assert_array_equal(gt.points, _mesh_points())
        np.testing.assert_array_equal(gt.semantic, EXPECTED_SEMANTIC)
        np.testing.assert_array_equal(gt.instance, EXPECTED_INSTANCE)

    def test_scannet_annotations_with_mesh_are_per_vertex(self, tmp_path: Path) -> None:
        labels_ply = _scannet_annotations(tmp_path / "ann")
        mesh = _mesh(tmp_path / f"{SCENE}_vh_clean_2.ply")
        report = import_scannet(
            _scan(tmp_path / SCENE),
            tmp_path / "b",
            ground_truth=labels_ply,
            geometry=mesh,
            vocabulary=builtin_vocabulary("scannet20"),
        )
        gt = open_bundle(report.bundle).read_ground_truth()
        assert gt is not None
        assert gt.points is None  # labels by vertex index, as the published evaluation
        np.testing.assert_array_equal(gt.instance, EXPECTED_INSTANCE)

    def test_npz_with_geometry(self, tmp_path: Path) -> None:
        mesh = _mesh(tmp_path / "mesh.ply")
        sem = np.array([0, 1, 2, 2, 1, 0, 0, 1, -1, 2])
        path = _npz(tmp_path / "gt.npz", semantic=sem, instance=np.arange(10))
        report = import_scannet(
            _scan(tmp_path / "s"), tmp_path / "b", ground_truth=path, geometry=mesh, vocabulary=_vocab()
        )
        gt = open_bundle(report.bundle).read_ground_truth()
        assert gt is not None
        np.testing.assert_array_equal(gt.semantic, sem)

    def test_exception(self, tmp_path: Path) -> None:
        src = _scan(tmp_path / "s")
        labels_ply = _scannet_annotations(tmp_path / "ann")
        with pytest.raises(InputError, match=r"labels\.ply: ScanNet annotations .* use --vocabulary scannet20"):
            import_scannet(src, tmp_path / "b1", ground_truth=labels_ply, vocabulary=_vocab())
        path = _npz(tmp_path / "gt.npz", semantic=np.zeros(10, np.int64), instance=np.zeros(10, np.int64))
        with pytest.raises(InputError, match=r"gt\.npz: semantic: .* pass --vocabulary"):
            import_scannet(src, tmp_path / "b2", ground_truth=path)
        small = write_ply(tmp_path / "mesh.ply", {k: np.zeros(3, np.float32) for k in "xyz"})
        with pytest.raises(InputError, match=r"gt\.npz: semantic: 10 labels .* geometry .*mesh\.ply \(3 vertices\)"):
            import_scannet(src, tmp_path / "b3", ground_truth=path, vocabulary=_vocab(), geometry=small)
        assert not (tmp_path / "b3").exists()  # checked before anything is written

    def test_cli(self, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
        labels_ply = _scannet_annotations(tmp_path / "ann")
        src, dst = _scan(tmp_path / SCENE), tmp_path / "b"
        assert cli_main(["import", "scannet", str(src), str(dst), "--gt", str(labels_ply)]) == 0
        assert "gt/labels.npz" in capsys.readouterr().out
        assert open_bundle(dst).has_ground_truth
        code = cli_main(["import", "scannet", str(src), str(tmp_path / "b2"), "--gt", str(labels_ply),
                         "--vocabulary", "matterport21"])  # fmt: skip
        assert code == 2
        assert "use --vocabulary scannet20" in capsys.readouterr().err


def _fake_run(out: Path, points: np.ndarray, semantic: np.ndarray, instance: np.ndarray, vocab: Vocabulary) -> Path:
    """The files of a finished run that evaluation reads."""
    out.mkdir(parents=True)
    write_ply(out / "panoptic.ply", {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]})
    np.savez(out / "labels.npz", semantic=semantic, instance=instance)
    write_vocabulary(out, vocab, "clip-vit-b32")
    return out


class TestEvalWithGroundTruth:
    def test_scannet_annotations_per_vertex(self, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
        labels_ply = _scannet_annotations(tmp_path / "ann")
        sem, ins = np.array(EXPECTED_SEMANTIC), np.array(EXPECTED_INSTANCE)
        run = _fake_run(tmp_path / "run", _mesh_points(), sem, ins, builtin_vocabulary("scannet20"))
        assert cli_main(["eval", str(run), "--gt", str(labels_ply), "--json"]) == 0
        metrics = json.loads(capsys.readouterr().out)
        assert metrics["standard"]["miou"] == pytest.approx(1.0)
        assert metrics["standard"]["prq_thing"] == pytest.approx(1.0)
        assert metrics["paper"]["prq_stuff"] == pytest.approx(1.0)

    def test_npz_points_transfer_by_nearest_primitive(self, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
        vocab = _vocab()
        prims = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
        pred_sem, pred_ins = np.array([0, 1, 1, 2]), np.array([-1, 0, 0, 1])
        run = _fake_run(tmp_path / "run", prims, pred_sem, pred_ins, vocab)
        gt_points = np.array([[0.1, 0, 0], [0.9, 0, 0], [2.2, 0, 0], [2.6, 0, 0], [3.3, 0, 0]], np.float32)
        gt_sem, gt_ins = np.array([0, 1, 1, 1, 2]), np.array([-1, 5, 5, 5, 6])
        gt = _npz(tmp_path / "gt.npz", semantic=gt_sem, instance=gt_ins, points=gt_points)
        assert cli_main(["eval", str(run), "--gt", str(gt), "--json"]) == 0
        metrics = json.loads(capsys.readouterr().out)
        nearest = np.array([0, 1, 2, 3, 3])
        expected = evaluate(pred_sem[nearest], pred_ins[nearest], gt_sem, gt_ins, vocab)
        assert metrics["standard"]["miou"] == pytest.approx(expected.miou)
        assert metrics["standard"]["prq_thing"] == pytest.approx(expected.prq_thing)
        assert cli_main(["eval", str(run), "--gt", str(gt)]) == 0
        assert "each from its nearest primitive" in capsys.readouterr().out

    def test_exception(self, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
        labels_ply = _scannet_annotations(tmp_path / "ann")
        run = _fake_run(tmp_path / "run", _mesh_points(), np.zeros(10, np.int64), np.zeros(10, np.int64), _vocab())
        assert cli_main(["eval", str(run), "--gt", str(labels_ply)]) == 2
        assert "use --vocabulary scannet20" in capsys.readouterr().err
        gt = _npz(tmp_path / "gt.npz", semantic=np.zeros(4, np.int64), instance=np.zeros(4, np.int64))
        assert cli_main(["eval", str(run), "--gt", str(gt)]) == 2
        assert "(10 vertices)" in capsys.readouterr().err
        assert cli_main(["eval", str(tmp_path / "nothing"), "--gt", str(gt)]) == 2
        assert "missing" in capsys.readouterr().err
