"""Tests of the synthetic scene generator (panogs_core.synthetic)."""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from panogs_core.errors import ConfigError, EncoderUnavailableError
from panogs_core.io.bundle import Bundle, open_bundle
from panogs_core.synthetic import CLASS_KINDS, CLASS_NAMES, PRESETS, SyntheticSpec, build_layout, make_scene
from panogs_core.synthetic.layout import NUM_STUFF
from panogs_core.synthetic.placement import Boxes, inside_room, overlaps
from panogs_core.synthetic.sampling import sample_surfaces

CLIP = "clip-vit-b32"  # no model to load: the label-set rows ship with the package


def _build(root: Path, **kw: object) -> tuple[Path, float]:
    t0 = time.perf_counter()
    path = make_scene(root, **{"preset": "tiny", "feature_space": CLIP, **kw})  # type: ignore[arg-type]
    return path, time.perf_counter() - t0


@pytest.fixture(scope="module")
def easy(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, float]:
    return _build(tmp_path_factory.mktemp("easy") / "scene", difficulty="easy", seed=0)


@pytest.fixture(scope="module")
def easy_scene(easy: tuple[Path, float]) -> Bundle:
    return open_bundle(easy[0])


def _pixels_world(scene: Bundle, frame_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Valid depth pixels of a frame: rows, columns and world points."""
    frame, cam = scene.frames[frame_index], scene.camera
    depth = scene.read_depth(frame)
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    cam_pts = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
    T = frame.T_world_cam
    return v, u, cam_pts @ T[:3, :3].T + T[:3, 3]


def _cells(v: np.ndarray, u: np.ndarray, shape: tuple[int, ...], scene: Bundle) -> tuple[np.ndarray, np.ndarray]:
    """docs/scene_format.md's pixel-to-cell rule."""
    rows = ((v + 0.5) * shape[0] / scene.camera.height).astype(np.int64)
    cols = ((u + 0.5) * shape[1] / scene.camera.width).astype(np.int64)
    return rows, cols


class TestBundle:
    def test_smoke(self, easy: tuple[Path, float]) -> None:
        root, seconds = easy
        assert seconds < 10.0, f"tiny scene took {seconds:.1f} s"
        for name in ("scene.json", "geometry.ply", "vocabulary.json", "vocabulary.npy", "gt/labels.npz"):
            assert (root / name).is_file(), name
        assert {p.name for p in root.iterdir()} >= {"color", "depth", "features", "masks"}

    def test_cardinality(self, easy_scene: Bundle) -> None:
        spec = PRESETS["tiny"]
        scene = easy_scene
        assert (scene.camera.width, scene.camera.height) == (spec.width, spec.height)
        assert len(scene.frames) == spec.num_frames == len(scene.feature_frames) == len(scene.mask_frames)
        assert scene.feature_space == CLIP
        assert scene.feature_dim == 512
        frame = scene.frames[0]
        assert scene.read_depth(frame).shape == (spec.height, spec.width)
        feats = scene.read_features(frame)
        stride = spec.feature_stride
        assert feats.shape == (spec.height // stride, spec.width // stride, 512)
        assert feats.dtype == np.float16
        np.testing.assert_allclose(np.linalg.norm(feats.astype(np.float32), axis=-1), 1.0, atol=2e-3)
        assert scene.read_masks(frame).shape == (spec.height, spec.width)
        geo, gt = scene.read_geometry(), scene.read_ground_truth()
        assert geo is not None
        assert gt is not None
        assert gt.points is None
        # 12k surface samples, of which only those some frame observes are kept (a scan holds what it saw)
        assert 5_000 <= len(geo.points) <= 12_000
        assert gt.semantic.shape == gt.instance.shape == (len(geo.points),)
        assert geo.normals is not None
        assert geo.colors is not None

    def test_vocabulary(self, easy_scene: Bundle) -> None:
        voc = easy_scene.vocabulary
        assert voc is not None
        assert voc.names == CLASS_NAMES
        assert voc.kinds == CLASS_KINDS
        assert {n for n, k in zip(voc.names, voc.kinds) if k == "stuff"} == {"wall", "floor", "ceiling"}
        assert voc.embeddings is not None
        assert voc.embeddings.shape == (len(CLASS_NAMES), 512)

    def test_poses(self, easy_scene: Bundle) -> None:
        for frame in easy_scene.frames:
            rot = frame.T_world_cam[:3, :3]
            np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-6)
            assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-6)
            assert 1.3 - 1e-6 <= frame.T_world_cam[2, 3] <= 1.7 + 1e-6
            assert rot[2, 1] < -0.5  # OpenCV: camera y (image down) points roughly down in the z-up world

    @pytest.mark.slow  # builds a tiny scene (1.5-2 s here)
    def test_without_geometry(self, tmp_path: Path) -> None:
        root, _ = _build(tmp_path / "scene", difficulty="easy", seed=0, with_geometry=False)
        assert not (root / "geometry.ply").exists()
        gt = open_bundle(root).read_ground_truth()
        assert gt is not None
        assert gt.points is not None
        assert gt.points.shape == (len(gt.semantic), 3)

    def test_exception(self, tmp_path: Path) -> None:
        with pytest.raises(ConfigError, match="preset"):
            make_scene(tmp_path / "a", preset="huge")
        with pytest.raises(ConfigError, match="difficulty"):
            make_scene(tmp_path / "b", difficulty="brutal")
        with pytest.raises(ValueError, match="feature_space"):
            make_scene(tmp_path / "c", feature_space="rgb")


class TestGroundTruth:
    def test_classes_and_instances(self) -> None:
        thing_classes: set[int] = set()
        for seed in range(4):
            layout = build_layout(PRESETS["tiny"], np.random.default_rng(seed))
            surface = sample_surfaces(layout, 5_000, np.random.default_rng(seed))
            kinds = np.array([CLASS_KINDS[c] for c in surface.semantic])
            assert set(np.unique(surface.instance[kinds == "stuff"])) == set(range(NUM_STUFF))
            # one class per instance, every instance has points
            pairs = np.unique(np.stack([surface.instance, surface.semantic], 1), axis=0)
            assert len(pairs) == len(np.unique(surface.instance)) == len(layout.instance_class)
            counts = np.bincount(layout.instance_class[NUM_STUFF:])
            assert counts.max() >= 2, "some class should have several instances"
            thing_classes |= set(layout.instance_class[NUM_STUFF:].tolist())
        assert len(thing_classes) >= 8

    def test_no_interpenetration(self) -> None:
        for preset, seed in (("tiny", 0), ("tiny", 1), ("default", 2), ("large", 3)):
            layout = build_layout(PRESETS[preset], np.random.default_rng(seed))
            b, idx = layout.boxes, np.arange(NUM_STUFF, len(layout.boxes.yaw))
            assert inside_room(Boxes(b.centers[idx], b.half[idx], b.yaw[idx]), layout.room)
            for k in idx:
                other = idx[layout.box_instance[idx] != layout.box_instance[k]]
                one = Boxes(b.centers[[k]], b.half[[k]], b.yaw[[k]])
                assert not overlaps(one, Boxes(b.centers[other], b.half[other], b.yaw[other]), -1e-4)

    def test_overlaps(self) -> None:
        a = Boxes(np.array([[0.0, 0.0, 0.5]]), np.array([[0.5, 0.5, 0.5]]), np.zeros(1))
        touching = Boxes(np.array([[1.0, 0.0, 0.5]]), np.array([[0.5, 0.5, 0.5]]), np.zeros(1))
        assert not overlaps(a, touching, 0.0)
        assert overlaps(a, touching, 0.01)
        # a diamond whose corner is 0.05 m from a's face: clear along x, but not by 0.1 m
        diamond = Boxes(np.array([[0.5 + 0.05 + 0.5 * np.sqrt(2), 0.0, 0.5]]), a.half, np.array([np.pi / 4]))
        assert not overlaps(a, diamond, 0.0)
        assert overlaps(a, diamond, 0.1)
        above = Boxes(np.array([[0.0, 0.0, 1.5]]), a.half, np.zeros(1))
        assert not overlaps(a, above, 0.0)


class TestViews:
    def test_backprojection(self, easy_scene: Bundle) -> None:
        geo = easy_scene.read_geometry()
        assert geo is not None
        assert geo.normals is not None
        tree = cKDTree(geo.points)
        dist = []
        for i in range(0, len(easy_scene.frames), 3):
            _, _, world = _pixels_world(easy_scene, i)
            _, nn = tree.query(world)
            dist.append(np.abs(np.sum((world - geo.points[nn]) * geo.normals[nn], axis=1)))
        assert np.median(np.concatenate(dist)) < 0.02

    def test_features_easy(self, easy_scene: Bundle) -> None:
        geo, gt, voc = easy_scene.read_geometry(), easy_scene.read_ground_truth(), easy_scene.vocabulary
        assert geo is not None
        assert gt is not None
        assert voc is not None
        assert voc.embeddings is not None
        tree = cKDTree(geo.points)
        hits = []
        for i, frame in enumerate(easy_scene.feature_frames):
            v, u, world = _pixels_world(easy_scene, i)
            feats = easy_scene.read_features(frame).astype(np.float32)
            rows, cols = _cells(v, u, feats.shape, easy_scene)
            pred = (feats[rows, cols] @ voc.embeddings.T).argmax(axis=1)
            hits.append(pred == gt.semantic[tree.query(world)[1]])
        assert np.concatenate(hits).mean() > 0.95

    def test_masks_easy(self, easy_scene: Bundle) -> None:
        geo, gt = easy_scene.read_geometry(), easy_scene.read_ground_truth()
        assert geo is not None
        assert gt is not None
        tree = cKDTree(geo.points)
        pure = total = 0
        for i, frame in enumerate(easy_scene.mask_frames):
            v, u, world = _pixels_world(easy_scene, i)
            masks = easy_scene.read_masks(frame)
            rows, cols = _cells(v, u, masks.shape, easy_scene)
            mask, inst = masks[rows, cols], gt.instance[tree.query(world)[1]]
            keep = mask > 0
            assert keep.mean() > 0.8, "easy masks should cover most of the image"
            pair, count = np.unique(np.stack([mask[keep], inst[keep]], 1), axis=0, return_counts=True)
            best = np.zeros(int(mask.max()) + 1, dtype=np.int64)
            np.maximum.at(best, pair[:, 0], count)
            pure, total = pure + best.sum(), total + keep.sum()
        assert pure / total > 0.95

    def test_all_instances_seen(self, easy_scene: Bundle) -> None:
        gt, geo = easy_scene.read_ground_truth(), easy_scene.read_geometry()
        assert gt is not None
        assert geo is not None
        tree = cKDTree(geo.points)
        seen = set()
        for i in range(len(easy_scene.frames)):
            seen |= set(gt.instance[tree.query(_pixels_world(easy_scene, i)[2])[1]].tolist())
        assert seen == set(np.unique(gt.instance).tolist())


@pytest.mark.slow  # each test builds another tiny scene (1.5-2 s here)
class TestDeterminism:
    def test_same_seed_same_bundle(self, easy: tuple[Path, float], tmp_path: Path) -> None:
        again, _ = _build(tmp_path / "again", difficulty="easy", seed=0)
        for rel in (
            "gt/labels.npz",
            "geometry.ply",
            "features/000005.npy",
            "masks/000005.png",
            "depth/000005.png",
        ):
            assert (again / rel).read_bytes() == (easy[0] / rel).read_bytes(), rel
        a, b = open_bundle(again), open_bundle(easy[0])
        np.testing.assert_array_equal(a.frames[7].T_world_cam, b.frames[7].T_world_cam)

    def test_other_seed_other_room(self, easy_scene: Bundle, tmp_path: Path) -> None:
        other, _ = _build(tmp_path / "other", difficulty="easy", seed=1)
        assert open_bundle(other).frames[0].T_world_cam.tolist() != easy_scene.frames[0].T_world_cam.tolist()

    def test_difficulty_degrades(self, easy_scene: Bundle, tmp_path: Path) -> None:
        hard = open_bundle(_build(tmp_path / "hard", difficulty="hard", seed=0)[0])
        same_room = hard.read_ground_truth()
        assert same_room is not None
        gt = easy_scene.read_ground_truth()
        assert gt is not None

        # difficulty changes the sensors, the 2D models and the walk (so which surfaces are observed), not the room
        def objects(g: object) -> dict[int, int]:
            return dict(zip(g.instance.tolist(), g.semantic.tolist(), strict=True))  # type: ignore[attr-defined]

        assert objects(same_room) == objects(gt)
        holes = [np.mean(s.read_depth(s.frames[3]) == 0) for s in (easy_scene, hard)]
        assert holes[1] > holes[0] + 0.02


@pytest.mark.slow
def test_minilm_space(tmp_path: Path) -> None:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        from panogs_core.language.text_encoders import encode_labels, get_text_encoder

        encoder = get_text_encoder("minilm-l6")
    except EncoderUnavailableError as exc:
        pytest.skip(str(exc))
    scene = open_bundle(make_scene(tmp_path / "m", preset="tiny", difficulty="easy", feature_space="minilm-l6"))
    assert scene.feature_space == "minilm-l6"
    assert scene.feature_dim == 384
    assert scene.read_features(scene.frames[0]).shape[-1] == 384
    assert scene.vocabulary is not None
    assert scene.vocabulary.embeddings is not None
    np.testing.assert_allclose(scene.vocabulary.embeddings, encode_labels(encoder, list(CLASS_NAMES)), atol=1e-5)


def test_geometry_holds_only_observed_surfaces(easy_scene: Bundle) -> None:
    """Every geometry point is seen by at least one frame (clean depth would show it; noisy easy depth too)."""
    from panogs_core.stages.visibility import VisibilityConfig, compute_visibility

    geo = easy_scene.read_geometry()
    assert geo is not None
    vis = compute_visibility(easy_scene, geo.points, VisibilityConfig(depth_rtol=0.05), frames=easy_scene.frames)
    seen = np.zeros(len(geo.points), dtype=bool)
    seen[vis.point_index] = True
    assert seen.mean() > 0.97


class TestTouchingSameClass:
    """Runs of touching objects of one class: where only the masks can tell instances apart."""

    def test_side_by_side_touches_and_lists_contacts(self) -> None:
        from panogs_core.synthetic import groups, shapes

        rng = np.random.default_rng(0)
        members = [groups.single(shapes.bookshelf(rng, 0.8, 0.3, 1.8)) for _ in range(3)]
        run = groups.side_by_side(members, rng)
        assert [m.cls for m in run.models] == ["bookshelf"] * 3
        assert run.contacts == [(0, 1), (1, 2)]
        x = sorted((m.bounds[0, 0], m.bounds[0, 1]) for m in run.models)
        gaps = [x[k + 1][0] - x[k][1] for k in range(2)]
        assert all(0.0 <= g <= 0.01 for g in gaps), gaps
        assert all(m.bounds[1, 0] == pytest.approx(0.0) for m in run.models)  # backs aligned on the wall

    def test_rooms_have_touching_same_class_objects(self) -> None:
        found = 0
        for seed in range(6):
            layout = build_layout(PRESETS["default"], np.random.default_rng(seed))
            cls = layout.instance_class
            found += int(np.sum(cls[layout.contacts[:, 0]] == cls[layout.contacts[:, 1]]))
        assert found >= 3

    def test_hidden_faces_between_touching_objects_are_not_in_the_geometry(self, easy_scene: Bundle) -> None:
        # Two objects 0-1 cm apart hide the faces that look at each other: a scan never captures them. No
        # geometry point of one instance may sit within 5 mm of a point of another instance with the
        # opposite normal (two faces facing each other across a gap).
        geo = easy_scene.read_geometry()
        gt = easy_scene.read_ground_truth()
        assert geo is not None
        assert gt is not None
        assert geo.normals is not None
        things = np.flatnonzero(gt.instance >= NUM_STUFF)
        tree = cKDTree(geo.points[things])
        pairs = tree.query_pairs(0.005, output_type="ndarray")
        a, b = things[pairs[:, 0]], things[pairs[:, 1]]
        facing = (gt.instance[a] != gt.instance[b]) & (np.einsum("ij,ij->i", geo.normals[a], geo.normals[b]) < -0.9)
        assert not facing.any()


def test_same_class_instances_look_alike() -> None:
    """Instance variation is a length: two instances of a class stay far more alike than two classes."""
    from panogs_core.synthetic.features import make_feature_model
    from panogs_core.synthetic.presets import DIFFICULTIES

    rng = np.random.default_rng(0)
    emb = rng.standard_normal((len(CLASS_NAMES), 384)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    noise = dataclasses.replace(DIFFICULTIES["default"].features, confused_instances=0.0)
    model = make_feature_model(emb, np.array([3] * 20), noise, rng)
    v = model.instance_vectors / np.linalg.norm(model.instance_vectors, axis=1, keepdims=True)
    cos = (v @ v.T)[~np.eye(20, dtype=bool)]
    # Random 384-d rows are sqrt(2) apart (s_c = 1.41), so the spread is 0.25 * 1.41 = 0.35: cosine about
    # 1 / (1 + 0.35^2) = 0.89 between two instances. The per-dimension sigma of 0.1 it replaced gave 0.13.
    assert cos.min() > 0.8


def test_old_presets_unchanged(easy_scene: Bundle) -> None:
    """The realistic preset must not move a byte of the older ones (benchmarks stay comparable).

    The numbers were read from a tiny / easy / seed 0 bundle made before the ``scan`` preset existed; counts
    must match exactly, sums to their printed precision (robust to last-bit differences between machines).
    """
    geo, gt = easy_scene.read_geometry(), easy_scene.read_ground_truth()
    assert geo is not None
    assert gt is not None
    frame = easy_scene.frames[5]
    depth, masks = easy_scene.read_depth(frame), easy_scene.read_masks(frame)
    feats = easy_scene.read_features(frame).astype(np.float32)
    assert len(geo.points) == 6855
    assert np.bincount(gt.semantic).tolist() == [2757, 758, 381, 369, 0, 358, 330, 290, 256, 239, 804, 143, 0, 0, 170]
    assert len(np.unique(gt.instance)) == 26
    np.testing.assert_allclose(geo.points.astype(np.float64).sum(axis=0), [15727.002, 10762.566, 7315.255], atol=2e-3)
    np.testing.assert_allclose(frame.T_world_cam[:3, 3], [1.717885, 2.460244, 1.447618], atol=2e-6)
    assert int((depth > 0).sum()) == 19089
    assert float(depth[depth > 0].mean()) == pytest.approx(2.009414, abs=2e-6)
    np.testing.assert_allclose(feats.mean(axis=(0, 1))[:4], [-0.01137, 0.00984, -0.00849, -0.00386], atol=2e-5)
    assert len(np.unique(masks)) == 14


class TestScanPreset:
    """The realistic preset: a dense capture of a cluttered studio, sparse key frames, unannotated truth."""

    @staticmethod
    def _small() -> SyntheticSpec:
        # the full preset takes ~30-40 s; the mechanisms show on a low-resolution, short capture of the room
        return dataclasses.replace(PRESETS["scan"], width=160, height=120, num_frames=24, num_points=20_000)

    @pytest.fixture(scope="class")
    def scan(self, tmp_path_factory: pytest.TempPathFactory) -> Bundle:
        root = tmp_path_factory.mktemp("scan") / "scene"
        return open_bundle(make_scene(root, preset=self._small(), difficulty="default", seed=0))

    @pytest.mark.slow  # the scan fixture builds a scene (1.5-2.5 s here)
    def test_frames(self, scan: Bundle) -> None:
        spec = PRESETS["scan"]
        assert spec.realistic
        assert spec.feature_space == CLIP
        assert spec.feature_stride == 4
        assert scan.feature_space == CLIP
        assert len(scan.frames) == 24
        assert len(scan.feature_frames) == len(scan.mask_frames) == 12  # every other frame is depth-only
        feats = scan.read_features(scan.feature_frames[0])
        assert feats.shape == (120 // 4, 160 // 4, 512)

    @pytest.mark.slow  # reads the scan fixture
    def test_unannotated_ground_truth(self, scan: Bundle) -> None:
        gt, geo = scan.read_ground_truth(), scan.read_geometry()
        assert gt is not None
        assert geo is not None
        unannotated = gt.semantic < 0
        np.testing.assert_array_equal(unannotated, gt.instance < 0)
        assert 0.1 < unannotated.mean() < 0.45
        # clutter sits off the walls and the floor: unannotated points in the middle of the room
        room_min, room_max = geo.points.min(axis=0), geo.points.max(axis=0)
        inner = (geo.points[:, :2] > room_min[:2] + 0.3).all(1) & (geo.points[:, :2] < room_max[:2] - 0.3).all(1)
        assert (unannotated & inner & (geo.points[:, 2] > 0.05)).sum() > 100
        assert gt.semantic.max() < len(CLASS_NAMES)

    @pytest.mark.slow  # reads the scan fixture
    def test_some_geometry_seen_by_no_key_frame(self, scan: Bundle) -> None:
        """The geometry comes from the dense trajectory; the sparse key frames miss part of it."""
        from panogs_core.stages.visibility import VisibilityConfig, compute_visibility

        geo = scan.read_geometry()
        assert geo is not None
        vis = compute_visibility(scan, geo.points, VisibilityConfig())
        seen = np.zeros(len(geo.points), dtype=bool)
        seen[vis.point_index] = True
        assert 0.1 < 1.0 - seen.mean() < 0.9

    def test_high_windows_sit_high_in_the_walls_and_leave_the_rest_as_drawn(self) -> None:
        from panogs_core.synthetic.catalog import CLASS_ID

        plain = build_layout(PRESETS["scan"], np.random.default_rng(0))
        walls = build_layout(PRESETS["scan-walls"], np.random.default_rng(0))
        n = len(plain.instance_class)
        np.testing.assert_array_equal(walls.instance_class[:n], plain.instance_class)  # drawn after all the rest
        added = np.arange(n, len(walls.instance_class))
        assert len(added) >= 2
        assert (walls.instance_class[added] == CLASS_ID["window"]).all()
        boxes = np.flatnonzero(np.isin(walls.box_instance, added))
        bottom = walls.boxes.centers[boxes, 2] - walls.boxes.half[boxes, 2]
        assert (bottom >= 1.5 - 1e-6).all()
        assert (walls.boxes.half[boxes].min(axis=1) <= 0.011).all()

    def test_bathroom_is_small_and_crowded(self) -> None:
        from panogs_core.synthetic.catalog import CLASS_ID

        spec = PRESETS["scan-bath"]
        for seed in (0, 1):
            layout = build_layout(spec, np.random.default_rng(seed))
            assert layout.room[0] * layout.room[1] < 11.0
            assert layout.annotated is not None
            things = layout.instance_class[NUM_STUFF:][layout.annotated[NUM_STUFF:]]
            assert {CLASS_ID[c] for c in ("bathtub", "toilet", "sink", "cabinet", "door")} <= set(things.tolist())
            assert len(things) >= 9  # the fixtures and cabinets of one small room
            assert (~layout.annotated[NUM_STUFF:]).sum() >= 3  # towels, bottles and bins
            b, idx = layout.boxes, np.arange(NUM_STUFF, len(layout.boxes.yaw))
            assert inside_room(Boxes(b.centers[idx], b.half[idx], b.yaw[idx]), layout.room)

    def test_lost_frames_are_a_run_of_key_frames(self) -> None:
        from panogs_core.synthetic.scan_scene import lost_frames

        rng = np.random.default_rng(3)
        assert lost_frames(40, 2, 0, rng) == frozenset()
        for _ in range(20):
            lost = sorted(lost_frames(40, 2, 2, rng))
            assert lost[0] % 2 == 0
            assert lost == list(range(lost[0], lost[0] + 3))  # two key frames and the frame between them
            assert lost[-1] < 40
        with pytest.raises(ConfigError, match="invalid_poses"):
            dataclasses.replace(PRESETS["scan-bath"], invalid_poses=20)  # every key frame lost
        with pytest.raises(ConfigError, match="room_kind"):
            dataclasses.replace(PRESETS["scan"], room_kind="garage")

    @pytest.mark.slow  # builds a small bathroom (about 3 s)
    def test_bathroom_bundle_lacks_the_lost_frames(self, tmp_path: Path) -> None:
        spec = dataclasses.replace(PRESETS["scan-bath"], width=160, height=120, num_frames=12,
                                   num_points=6000, invalid_poses=2)  # fmt: skip
        scene = open_bundle(make_scene(tmp_path / "bath", preset=spec, difficulty="default", seed=0))
        ids = [int(f.id) for f in scene.frames]
        assert len(ids) == 12 - 3
        missing = sorted(set(range(12)) - set(ids))
        assert missing == list(range(missing[0], missing[0] + 3))
        assert len(scene.feature_frames) == 6 - 2
        geo = scene.read_geometry()
        assert geo is not None
        assert len(geo.points) > 1000  # the mesh still holds what the lost frames saw

    def test_layout(self) -> None:
        from panogs_core.synthetic.catalog import CLASS_ID

        for seed in (0, 1):
            layout = build_layout(PRESETS["scan"], np.random.default_rng(seed))
            assert layout.annotated is not None
            assert not layout.annotated[1]  # the ceiling, as ScanNet's 20 classes have none
            assert (~layout.annotated[NUM_STUFF:]).sum() >= 20  # clutter
            things = layout.instance_class[NUM_STUFF:][layout.annotated[NUM_STUFF:]]
            assert {CLASS_ID[c] for c in ("cabinet", "counter", "sink", "bed", "sofa", "table", "curtain")} <= set(
                things.tolist()
            )
            assert (things == CLASS_ID["cabinet"]).sum() >= 4
            # the sink stands on the counter: they are listed as touching
            sink = np.flatnonzero(layout.instance_class == CLASS_ID["sink"])
            counter = np.flatnonzero(layout.instance_class == CLASS_ID["counter"])
            pairs = {tuple(sorted(p)) for p in layout.contacts.tolist()}
            assert any(tuple(sorted((int(s), int(c)))) in pairs for s in sink for c in counter)
            b, idx = layout.boxes, np.arange(NUM_STUFF, len(layout.boxes.yaw))
            assert inside_room(Boxes(b.centers[idx], b.half[idx], b.yaw[idx]), layout.room)
            for k in idx:
                other = idx[layout.box_instance[idx] != layout.box_instance[k]]
                one = Boxes(b.centers[[k]], b.half[[k]], b.yaw[[k]])
                assert not overlaps(one, Boxes(b.centers[other], b.half[other], b.yaw[other]), -1e-4)

    def test_realistic_difficulties(self) -> None:
        from panogs_core.synthetic.presets import DIFFICULTIES, REALISTIC_DIFFICULTIES, get_difficulty

        assert get_difficulty("hard", realistic=True) is REALISTIC_DIFFICULTIES["hard"]
        assert get_difficulty("hard") is DIFFICULTIES["hard"]
        for name, level in DIFFICULTIES.items():
            assert level.features.anchored_area == 0.0  # the realism strengths are off outside realistic specs
            assert level.trajectory.pose_error_m == 0.0
            assert REALISTIC_DIFFICULTIES[name].depth == level.depth  # same sensors
        areas = [REALISTIC_DIFFICULTIES[n].features.anchored_area for n in ("easy", "default", "hard")]
        assert areas == sorted(areas)
        assert areas[-1] > 0


def test_anchored_confusion_is_the_same_in_every_view() -> None:
    """Inside a world-anchored region a class leans to the same related class in every frame."""
    from panogs_core.synthetic.anchored import Anchors, synthesize_anchored_features
    from panogs_core.synthetic.catalog import CLASS_ID, RELATED
    from panogs_core.synthetic.features import make_feature_model
    from panogs_core.synthetic.presets import FeatureNoise

    rng = np.random.default_rng(0)
    emb = rng.standard_normal((len(CLASS_NAMES), 64)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    cabinet = CLASS_ID["cabinet"]
    noise = FeatureNoise(instance_spread=0.1, view_sigma=0.05, pixel_sigma=0.1, confused_instances=0.0,
                         confused_area=0.0, blur_cells=0.0)  # fmt: skip
    model = make_feature_model(emb, np.array([cabinet]), noise, rng, related=True)
    anchors = Anchors(centres=np.array([[0.0, 0.0, 0.0]]), radii=np.array([1.0]), pick=np.array([0.0]),
                      weight=np.array([0.8]))  # fmt: skip
    instance = np.zeros((8, 16), dtype=np.int64)
    world = np.zeros((8, 16, 3))
    world[:, 8:, 0] = 5.0  # the right half of the image lies outside the region
    target = CLASS_ID[RELATED["cabinet"][0]]
    for seed in range(4):
        feats = synthesize_anchored_features(model, anchors, np.array([True]), instance, world, (4, 8),
                                             np.random.default_rng(seed))  # fmt: skip
        pred = (feats.astype(np.float32) @ emb.T).argmax(axis=-1)
        assert (pred[:, :4] == target).all()
        assert (pred[:, 4:] == cabinet).all()
    # clutter (an unannotated instance) never leans
    feats = synthesize_anchored_features(model, anchors, np.array([False]), instance, world, (4, 8),
                                         np.random.default_rng(0))  # fmt: skip
    assert ((feats.astype(np.float32) @ emb.T).argmax(axis=-1) == cabinet).all()


def test_related_table() -> None:
    from panogs_core.synthetic.catalog import CLASS_ID, RELATED

    assert set(RELATED) == set(CLASS_NAMES)
    assert all(c in CLASS_ID and c != name for name, related in RELATED.items() for c in related)
    assert {"counter", "desk", "table"} <= set(RELATED["cabinet"])
    assert "wall" in RELATED["door"]
    assert {"curtain", "wall"} <= set(RELATED["window"])
