"""Tiled runs: the plan (cores, halos, frames, the budget), the merge (seams, classes, stuff) and a tiled run end to
end on a small synthetic building (docs/method.md §16)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from shared_runs import BUILDING_SPACE, BUILDING_TILED_ARGV
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture: the language field on a shared host)

from panogs_core.cli import main as cli_main
from panogs_core.errors import ConfigError, InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.stages.visibility import VisibilityConfig, compute_visibility
from panogs_core.synthetic import make_scene
from panogs_core.tiling.choice import parse_tiles
from panogs_core.tiling.merge import TileLabels, merge_tiles
from panogs_core.tiling.plan import TilePlan, TilingConfig, plan_tiles
from panogs_core.tiling.runner import run_tiled
from panogs_core.tiling.view import tile_bundle
from panogs_core.types import InstanceInfo, Vocabulary

SPACE = BUILDING_SPACE  # the label-set space needs no text encoder
NO_FIT = PipelineConfig().with_overrides({"appearance": {"enabled": False}})
EXACT = TilingConfig(sample_points=10**9)  # no sampling: the planner's counts are exact


@pytest.fixture(scope="module")
def building(tiny_building: Path) -> Path:
    """Two tiny rooms side by side, joined by a doorway (about 17k points, 28 frames; the session's: only read)."""
    return tiny_building


@pytest.fixture(scope="module")
def points(building: Path) -> np.ndarray:
    geometry = open_bundle(building).read_geometry()
    assert geometry is not None
    return geometry.points


def _box_distance(points: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """Chebyshev distance in XY from each point to a rectangle (0 inside)."""
    x0, x1, y0, y1 = box
    dx = np.maximum(np.maximum(x0 - points[:, 0], points[:, 0] - x1), 0)
    dy = np.maximum(np.maximum(y0 - points[:, 1], points[:, 1] - y1), 0)
    return np.maximum(dx, dy)


def test_cores_partition_the_primitives(building: Path, points: np.ndarray) -> None:
    plan = plan_tiles(open_bundle(building), EXACT, (2, 2), points=points)
    assert plan.tiled
    assert len(plan.tiles) == 4
    owner = plan.core_of(points)
    assert (owner >= 0).all()
    assert sum(t.core_points for t in plan.tiles) == points.shape[0]
    for tile in plan.tiles:
        index, core = plan.members(tile, points)
        assert np.array_equal(index[core], np.flatnonzero(owner == tile.index))
        assert (np.diff(index) > 0).all()
        # a core is bounded: its rectangle holds its points
        assert (_box_distance(points[index[core]], tile.core_box) <= 1e-4).all()
    # balanced by primitives: no tile holds more than twice another's core
    sizes = [t.core_points for t in plan.tiles]
    assert max(sizes) < 2 * min(sizes)


def test_halo_is_the_band_around_the_core(building: Path, points: np.ndarray) -> None:
    plan = plan_tiles(open_bundle(building), EXACT, (2, 1), points=points)
    for tile in plan.tiles:
        index, core = plan.members(tile, points)
        halo = index[~core]
        assert tile.halo_points == halo.size > 0
        distance = _box_distance(points, tile.core_box)
        assert (distance[halo] > 0).all()
        assert (distance[halo] <= EXACT.halo_m + 1e-4).all()
        band = np.flatnonzero((distance > 1e-4) & (distance < EXACT.halo_m - 1e-4))
        assert np.isin(band, halo).all()


def test_each_tile_gets_the_frames_that_see_it(building: Path, points: np.ndarray) -> None:
    bundle = open_bundle(building)
    plan = plan_tiles(bundle, EXACT, (2, 1), points=points)
    vis = compute_visibility(bundle, points, VisibilityConfig())
    for tile in plan.tiles:
        index, _ = plan.members(tile, points)
        member = np.zeros(points.shape[0], bool)
        member[index] = True
        sees = {vis.frame_ids[v] for v in range(vis.num_frames) if member[vis.frame(v)[0]].sum() >= 50}
        assert set(tile.frame_ids) == sees
        assert 0 < len(tile.frame_ids) < len(bundle.frames)  # a tile gets only some of the frames
    view, core = tile_bundle(bundle, plan, plan.tiles[0], points)
    geometry = view.read_geometry()
    assert geometry is not None
    assert geometry.points.shape[0] == core.size
    assert [f.id for f in view.frames] == list(plan.tiles[0].frame_ids)


def test_a_scene_under_the_budget_is_not_tiled(building: Path, points: np.ndarray) -> None:
    plan = plan_tiles(open_bundle(building), TilingConfig(), "auto", points=points)
    assert not plan.tiled
    assert len(plan.tiles) == 1
    assert plan.tiles[0].core_points == points.shape[0]


def test_auto_leaves_whole_a_scene_over_the_tile_target_that_fits_the_whole_limit(
    building: Path, points: np.ndarray
) -> None:
    bundle = open_bundle(building)
    whole = 74.0 * points.shape[0] * len(bundle.frames)
    small_tiles = {"memory_target_bytes": 0.4 * whole, "fixed_bytes": 0.0}
    assert not plan_tiles(bundle, TilingConfig(**small_tiles, whole_limit_bytes=2 * whole), "auto", points=points).tiled
    assert plan_tiles(bundle, TilingConfig(**small_tiles, whole_limit_bytes=0.5 * whole), "auto", points=points).tiled
    assert TilingConfig().whole_limit() >= TilingConfig().memory_target_bytes


def test_auto_splits_until_every_tile_fits(building: Path, points: np.ndarray) -> None:
    bundle = open_bundle(building)
    whole = 74.0 * points.shape[0] * len(bundle.frames)
    cfg = TilingConfig(
        memory_target_bytes=0.4 * whole, whole_limit_bytes=0.4 * whole, fixed_bytes=0.0, sample_points=10**9
    )
    plan = plan_tiles(bundle, cfg, "auto", points=points)
    assert plan.tiled
    assert len(plan.tiles) >= 3
    assert all(t.estimated_bytes <= cfg.memory_target_bytes for t in plan.tiles)
    assert sum(t.core_points for t in plan.tiles) == points.shape[0]


def test_settings_and_tile_names_are_checked() -> None:
    with pytest.raises(ConfigError, match=r"tiling\.halo_m"):
        TilingConfig(halo_m=0.3, cell_m=0.25)
    with pytest.raises(ConfigError, match=r"tiling\.fixed_bytes"):
        TilingConfig(fixed_bytes=4e9, memory_target_bytes=3e9)
    assert parse_tiles("3x1") == (3, 1)
    assert parse_tiles("off") == "off"
    for bad in ("0x2", "2x", "x2", "two", "2x2x2"):
        with pytest.raises(ValueError, match="--tiles"):
            parse_tiles(bad)


def test_forced_tiles_need_geometry(tmp_path: Path) -> None:
    bundle = make_scene(tmp_path / "t", preset="tiny", feature_space=SPACE, with_geometry=False)
    with pytest.raises(InputError, match="geometry"):
        run_tiled(bundle, tmp_path / "run", NO_FIT, tiles=(2, 1))


# --- the merge, on labels made by hand -------------------------------------------------------------------------

VOCAB = Vocabulary(names=("wall", "chair", "table"), kinds=("stuff", "thing", "thing"))


def _info(k: int, cls: int, n: int, feature: list[float]) -> InstanceInfo:
    zero = np.zeros(3, np.float32)
    return InstanceInfo(id=k, class_index=cls, class_name=VOCAB.names[cls], kind=VOCAB.kinds[cls], score=0.5,
                        num_points=n, centroid=zero, bbox_min=zero, bbox_max=zero,
                        feature=np.asarray(feature, np.float32))  # fmt: skip


def _two_tiles(object_class_right: int) -> tuple[list[TileLabels], np.ndarray]:
    """A line of 40 points along x with a seam at x = 20 (the halo 4 points wide): points 0-9 and 30-39 are wall,
    10-29 an object cut by the seam, a chair in the left tile and ``object_class_right`` in the right one."""
    points = np.stack([np.arange(40.0), np.zeros(40), np.zeros(40)], 1).astype(np.float32)
    wall = np.r_[0:10, 30:40]
    semantic = np.full(40, 1)
    semantic[wall] = 0
    left_index, right_index = np.arange(0, 24), np.arange(16, 40)
    left = TileLabels(
        point_index=left_index, core=left_index < 20, semantic=semantic[left_index],
        instance=np.where(semantic[left_index] == 0, 1, 0), superprimitive=np.zeros(24, np.int64),
        cluster=np.zeros(24, np.int64), instances=(_info(0, 1, 14, [1, 0]), _info(1, 0, 10, [0, 1])),
    )  # fmt: skip
    right_semantic = np.where(semantic[right_index] == 0, 0, object_class_right)
    right = TileLabels(
        point_index=right_index, core=right_index >= 20, semantic=right_semantic,
        instance=np.where(right_semantic == 0, 0, 1), superprimitive=np.zeros(24, np.int64),
        cluster=np.full(24, 3, np.int64),
        instances=(_info(0, 0, 10, [0, 1]), _info(1, object_class_right, 14, [0.6, 0.8])),
    )  # fmt: skip
    return [left, right], points


def test_an_instance_cut_by_a_seam_is_joined() -> None:
    tiles, points = _two_tiles(object_class_right=1)
    merged = merge_tiles(tiles, points, VOCAB, min_overlap=4)
    labels = merged.labels
    assert merged.seam_joins == 1
    assert len(set(labels.instance[10:30].tolist())) == 1
    kinds = sorted((i.class_name, i.num_points) for i in labels.instances)
    assert kinds == [("chair", 20), ("wall", 20)]  # the walls at both ends are one stuff segment
    chair = next(i for i in labels.instances if i.class_name == "chair")
    assert chair.id == 0
    assert labels.instance[10] == 0
    # the feature is the pieces' average by their core points (10 each), made unit
    assert np.allclose(chair.feature, np.array([1.6, 0.8]) / np.linalg.norm([1.6, 0.8]), atol=1e-6)
    assert np.allclose(chair.bbox_min, [10, 0, 0])
    assert np.allclose(chair.bbox_max, [29, 0, 0])
    assert merged.cluster[0] == 0
    assert merged.cluster[39] == 4


def test_different_classes_across_a_seam_stay_apart() -> None:
    tiles, points = _two_tiles(object_class_right=2)
    merged = merge_tiles(tiles, points, VOCAB, min_overlap=4)
    assert merged.seam_joins == 0
    assert sorted(i.class_name for i in merged.labels.instances) == ["chair", "table", "wall"]
    assert merged.labels.semantic[15] == 1
    assert merged.labels.semantic[25] == 2


def test_a_small_overlap_is_no_join() -> None:
    tiles, points = _two_tiles(object_class_right=1)
    assert merge_tiles(tiles, points, VOCAB, min_overlap=9).seam_joins == 0  # 8 shared points


# --- end to end ---------------------------------------------------------------------------------------------------


TILED_ARGV = list(BUILDING_TILED_ARGV)  # --tiles 2x1, no appearance fit


@pytest.fixture(scope="module")
def tiled_run(tiny_building_tiled_run: Path) -> Path:
    """``panogs run --tiles 2x1`` of the building, tiles one after another (the default; the session's, shared
    with tests/worker/test_tiled_jobs.py): only read here, copied by the test that runs it again."""
    return tiny_building_tiled_run


@pytest.mark.slow
def test_tiled_cli_run_is_deterministic_in_one_process_or_two_and_reported(
    building: Path, tiled_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from panogs_core.tiling import runner

    runs = [tiled_run, tmp_path / "b"]  # one after another (the fixture's), then side by side
    argv = ["run", str(building), "--out", str(runs[1]), *TILED_ARGV, "--tile-workers", "2"]
    at_hash: list[object] = []
    real_hash = runner.hash_bundle

    def hash_after_the_results(scene: object) -> str:  # the results' report is written first, without the hash
        at_hash.append(json.loads((runs[1] / "report.json").read_text())["input_sha256"])
        return real_hash(scene)  # type: ignore[arg-type]

    monkeypatch.setattr(runner, "hash_bundle", hash_after_the_results)
    assert cli_main(argv) == 0
    assert at_hash == [None]
    assert json.loads((runs[1] / "report.json").read_text())["input_sha256"] == real_hash(open_bundle(building))
    for name in ("labels.npz", "instances.json", "instance_features.npy", "panoptic.ply"):
        assert (runs[0] / name).read_bytes() == (runs[1] / name).read_bytes(), name
    report = json.loads((runs[0] / "report.json").read_text())
    tiles = report["tiling"]["tiles"]
    plan = TilePlan.load(runs[0] / "tiles" / "plan.json")
    assert [t.name for t in plan.tiles] == [t["name"] for t in tiles]
    assert all((runs[0] / "tiles" / t["name"] / "labels.npz").is_file() for t in tiles)
    assert report["tiling"]["tiled"]
    assert len(tiles) == 2
    assert sum(t["core_primitives"] for t in tiles) == report["num_primitives"]
    for tile in tiles:
        assert tile["halo_primitives"] > 0
        assert tile["frames"] > 0
        assert tile["wall_s"] > 0
        assert tile["peak_rss_mb"] > 0
    labels = np.load(runs[0] / "labels.npz")
    instances = json.loads((runs[0] / "instances.json").read_text())
    assert [i["id"] for i in instances] == list(range(len(instances)))
    assert set(np.unique(labels["instance"])) - {-1} == set(range(len(instances)))
    stuff = [i["class_name"] for i in instances if i["kind"] == "stuff"]
    assert len(stuff) == len(set(stuff))  # one segment per stuff class across the building
    metrics = json.loads((runs[0] / "metrics.json").read_text())
    assert metrics["standard"]["miou"] > 0.6


def test_a_finished_tile_keeps_only_what_the_merge_reads_and_is_not_run_again(
    building: Path, tiled_run: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    shutil.copytree(tiled_run, out)  # the same argv's run, finished (a tile's files name nothing outside it)
    argv = ["run", str(building), "--out", str(out), *TILED_ARGV]
    plan = TilePlan.load(out / "tiles" / "plan.json")
    folders = [out / "tiles" / t.name for t in plan.tiles]
    for folder in folders:  # the (N, D) features of the fusion and the field are gone, the primitives stay
        assert sorted(p.stem for p in (folder / "stages").glob("*.npz")) == [
            "clustering", "labeling", "primitives", "superprimitives"]  # fmt: skip
    labels = (out / "labels.npz").read_bytes()
    stamps = [(f / "labels.npz").stat().st_mtime_ns for f in folders]
    assert cli_main(argv) == 0  # the same run again: its tiles are finished
    assert [(f / "labels.npz").stat().st_mtime_ns for f in folders] == stamps
    assert (out / "labels.npz").read_bytes() == labels
    assert cli_main([*argv, "--set", "clustering.thresholds=[0.9,0.6]"]) == 0  # other settings: the tiles run again
    assert all((f / "labels.npz").stat().st_mtime_ns != t for f, t in zip(folders, stamps, strict=True))


@pytest.mark.slow
def test_untiled_path_is_unchanged(building: Path, tiny_building_plain_run: Path, tmp_path: Path) -> None:
    tiled = run_tiled(building, tmp_path / "auto", NO_FIT, tiles="auto")
    plain = tiny_building_plain_run  # run_pipeline(building, ..., NO_FIT), the session's
    assert tiled.num_primitives == json.loads((plain / "report.json").read_text())["num_primitives"]
    for name in ("labels.npz", "instances.json", "instance_features.npy"):
        assert (tmp_path / "auto" / name).read_bytes() == (plain / name).read_bytes(), name
    assert "tiling" not in json.loads((tmp_path / "auto" / "report.json").read_text())


# --- the synthetic building -----------------------------------------------------------------------------------


def test_building_rooms_are_joined_by_a_doorway(building: Path, points: np.ndarray) -> None:
    bundle = open_bundle(building)
    gt = bundle.read_ground_truth()
    assert gt is not None
    assert bundle.vocabulary is not None
    stuff = {n for n, k in zip(bundle.vocabulary.names, bundle.vocabulary.kinds, strict=True) if k == "stuff"}
    # the six stuff instances of each room come first: floor, ceiling, four walls, room by room
    for instance in range(12):
        classes = {bundle.vocabulary.names[c] for c in np.unique(gt.semantic[gt.instance == instance])}
        assert classes <= stuff
    assert not ({bundle.vocabulary.names[c] for c in np.unique(gt.semantic[gt.instance >= 12])} & stuff)
    floor0, floor1 = points[gt.instance == 0], points[gt.instance == 6]
    seam = (floor0[:, 0].max() + floor1[:, 0].min()) / 2
    # the shared walls' faces, below the lintel: a gap at least 0.9 m wide along y is the doorway
    wall = (gt.instance == 3) & (points[:, 2] > 0.2) & (points[:, 2] < 1.9)
    ys = np.sort(points[wall, 1])
    assert np.diff(ys).max() >= 0.9
    # key frames of the first room see into the second through it
    vis = compute_visibility(bundle, points, VisibilityConfig())
    first_room = [v for v in range(vis.num_frames) if bundle.frames[v].T_world_cam[0, 3] < seam]
    beyond = [(points[vis.frame(v)[0], 0] > seam + 0.5).sum() for v in first_room]
    assert max(beyond) > 100


def test_the_cli_refuses_bad_tiles_and_rooms(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli_main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--tiles", "2by2"])
    assert "--tiles: expected auto, off or NxM" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["synth", str(tmp_path / "b"), "--preset", "building", "--rooms", "0x2"])
    assert "expected N or NxM rooms" in capsys.readouterr().err


def test_a_tiles_input_hash_follows_its_scene_and_where_it_lies(building: Path, points: np.ndarray) -> None:
    from panogs_core.tiling.tile import tile_input_hash

    plan = plan_tiles(open_bundle(building), EXACT, (2, 1), points=points)
    first, second = plan.tiles
    made = tile_input_hash("a" * 64, plan, first)
    assert made == tile_input_hash("a" * 64, plan, first)
    assert len(made) == 64
    assert made != tile_input_hash("b" * 64, plan, first)  # another scene
    assert made != tile_input_hash("a" * 64, plan, second)  # another tile


def test_a_saved_plan_rebuilds_the_same_tiles(building: Path, points: np.ndarray, tmp_path: Path) -> None:
    plan = plan_tiles(open_bundle(building), EXACT, (2, 1), points=points)
    plan.save(tmp_path / "plan.json")
    again = TilePlan.load(tmp_path / "plan.json")
    assert again == plan
    assert np.array_equal(again.core_of(points), plan.core_of(points))
