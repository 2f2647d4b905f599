"""Building-scale benchmark: one synthetic building planned into tiles, run with several tile processes, then some of
its rooms run alone (docs/method.md §16, docs/benchmarks.md "A building at the design's scale").

Usage:
    python bench/building.py [--rooms 4x4] [--seed 0] [--tile-workers 2] [--alone 4] [--room-tile HALO[,K=V...]]
                             [--set SECTION.KEY=VALUE ...] [--root /work/bench-building]

``panogs synth --preset building --rooms NxM --room-preset large`` (kept under ``--root``), then ``panogs run
--tiles auto --tile-workers N`` (appearance fit off: a tiled run fits none) in its own process, timed. Prints the
plan (tiles, their primitives and frames), every tile's and the merge's peak memory and wall time, the whole run's
wall time and peak, and its standard-mode metrics. Then ``--alone`` rooms (spread over the grid: corners first)
each run alone, untiled: the room's primitives (its floor's rectangle in XY, walls included) and the frames whose
camera stands in it; its mIoU, PRQ(T) and PRQ(S) against the building run's labels of the same primitives, scored
against the same ground truth. ``--room-tile`` runs each of those rooms also as one tile of its own (its
rectangle, a halo, the frames the planner would give it) with pipeline overrides, to tell what a tile's context
(halo, other rooms' frames, settings) does to a room.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.io.bundle import open_bundle  # noqa: E402

ROOM_MARGIN_M = 0.3  # the floor's rectangle grown by this, so that the room's walls are the room's
CELL_M = 0.02  # grid of the one-tile plan that cuts a room out


def _beside(run: Path, suffix: str) -> Path:
    """A file next to a run folder (``with_suffix`` would cut a folder name with a dot, such as ``...-0.15``)."""
    return run.with_name(run.name + suffix)


def _cli(*args: str) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "panogs_core.cli", *args], cwd=REPO, check=True)
    return time.perf_counter() - start


def _room_boxes(bundle: Path) -> list[tuple[float, float, float, float]]:
    """(x0, x1, y0, y1) of every room: the XY rectangle of each floor instance, grown by ROOM_MARGIN_M, in the
    generator's room order (along x first)."""
    from panogs_core.pipeline.run import resolve_scene_vocabulary

    scene = open_bundle(bundle)
    gt = scene.read_ground_truth()
    geometry = scene.read_geometry()
    assert gt is not None
    assert geometry is not None
    points = geometry.points if gt.points is None else gt.points
    floor = resolve_scene_vocabulary(scene, None).names.index("floor")
    boxes = []
    for inst in np.unique(gt.instance[gt.semantic == floor]):
        xy = points[gt.instance == inst, :2]
        lo, hi = xy.min(axis=0) - ROOM_MARGIN_M, xy.max(axis=0) + ROOM_MARGIN_M
        boxes.append((float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])))
    return sorted(boxes, key=lambda b: (round(b[2], 1), b[0]))


def _spread(count: int, rooms: int, nx: int) -> list[int]:
    """Rooms to run alone: the corners, then the rest from the middle out."""
    ny = rooms // nx
    corners = [0, nx - 1, rooms - nx, rooms - 1]
    middle = sorted(range(rooms), key=lambda r: abs(r % nx - (nx - 1) / 2) + abs(r // nx - (ny - 1) / 2))
    order = list(dict.fromkeys([*corners, *middle]))
    return sorted(order[:count])


def _room_view(scene: Any, points: np.ndarray, box: tuple[float, ...], cell_m: float, halo_m: float,
               frame_ids: Any) -> tuple[Any, np.ndarray]:  # fmt: skip
    """The bundle of one tile whose core is the room's rectangle ``box``, grown by ``halo_m``, with ``frame_ids``
    (a callable of the tile's cell rectangle and halo cells, so it can ask the planner's counts), and its core."""
    from panogs_core.tiling.plan import TilePlan, TileSpec
    from panogs_core.tiling.view import tile_bundle

    lo = points[:, :2].min(axis=0).astype(np.float64)
    grid = tuple(int(v) for v in np.floor((points[:, :2].max(axis=0) - lo) / cell_m) + 1)
    h = round(halo_m / cell_m)
    cell = lambda v, o: int(np.floor((v - o) / cell_m))  # noqa: E731
    rect = (cell(box[0], lo[0]), cell(box[1], lo[0]) + 1, cell(box[2], lo[1]), cell(box[3], lo[1]) + 1)
    grown = (box[0] - halo_m, box[1] + halo_m, box[2] - halo_m, box[3] + halo_m)
    spec = TileSpec(index=0, core_cells=rect, core_box=box, halo_box=grown, core_points=0, halo_points=0,
                    frame_ids=tuple(frame_ids(lo, grid, rect, h)), estimated_bytes=0.0)  # fmt: skip
    plan = TilePlan(origin=(float(lo[0]), float(lo[1])), cell_m=cell_m, halo_cells=h, grid=grid, tiles=(spec,),
                    tiled=True, reason="one room", whole_estimated_bytes=0.0)  # fmt: skip
    return tile_bundle(scene, plan, spec, points)


def _overrides(sets: tuple[str, ...]) -> Any:
    import yaml

    from panogs_core.pipeline.config import PipelineConfig

    overrides: dict[str, Any] = {"appearance": {"enabled": False}}
    for kv in sets:
        key, value = kv.split("=", 1)
        section, name = key.split(".", 1)
        overrides.setdefault(section, {})[name] = yaml.safe_load(value)
    return PipelineConfig().with_overrides(overrides)


def _room_alone(bundle: str, out: str, x0: str, x1: str, y0: str, y1: str, *sets: str) -> None:
    """``--one-room``: the room's primitives and the frames standing in it, run untiled (its own process), with
    the overrides ``sets``."""
    from panogs_core.pipeline.run import run_pipeline
    from panogs_core.tiling.plan import key_frames

    scene = open_bundle(bundle)
    geometry = scene.read_geometry()
    assert geometry is not None
    box = tuple(float(v) for v in (x0, x1, y0, y1))

    def standing_inside(*_: Any) -> list[str]:
        return [f.id for f in key_frames(scene)
                if box[0] <= f.T_world_cam[0, 3] < box[1] and box[2] <= f.T_world_cam[1, 3] < box[3]]  # fmt: skip

    view, _ = _room_view(scene, geometry.points, box, CELL_M, 0.0, standing_inside)
    np.save(_beside(Path(out), ".index.npy"), view.point_index)
    run_pipeline(view, out, _overrides(sets))


def _room_tile(bundle: str, out: str, x0: str, x1: str, y0: str, y1: str, halo: str, *sets: str) -> None:
    """``--one-room-tile``: the room as one tile of its own: core its rectangle, a halo of ``halo`` m, the frames
    the planner would give it (those that see ``min_frame_points`` of its core and halo), with overrides ``sets``
    (``SECTION.KEY=VALUE``); untiled, in its own process."""
    from panogs_core.pipeline.run import run_pipeline
    from panogs_core.tiling.plan import TilingConfig, _cell_counts, key_frames

    scene = open_bundle(bundle)
    geometry = scene.read_geometry()
    assert geometry is not None
    cfg = TilingConfig()
    frames = key_frames(scene)

    def planner_frames(lo: np.ndarray, grid: tuple[int, int], rect: tuple[int, ...], h: int) -> list[str]:
        counts = _cell_counts(scene, geometry.points, frames, lo, grid, cfg, None)
        seeing = counts.frames_seeing(rect[0] - h, rect[1] + h, rect[2] - h, rect[3] + h, cfg.min_frame_points)
        return [frames[k].id for k in seeing]

    box = tuple(float(v) for v in (x0, x1, y0, y1))
    view, core = _room_view(scene, geometry.points, box, cfg.cell_m, float(halo), planner_frames)
    np.save(_beside(Path(out), ".index.npy"), view.point_index)
    np.save(_beside(Path(out), ".core.npy"), core)
    run_pipeline(view, out, _overrides(sets))


def _room_tile_miou(bundle: Path, alone: Path, variant: Path) -> tuple[float, int]:
    """mIoU of the room's primitives (those of the alone run) labelled by the room-tile run's core."""
    from panogs_core.pipeline.run import resolve_scene_vocabulary
    from panogs_core.tiling.view import TileBundle

    scene = open_bundle(bundle)
    vocab = resolve_scene_vocabulary(scene, None)
    geometry = scene.read_geometry()
    assert geometry is not None
    room = np.load(_beside(alone, ".index.npy"))
    index, core = np.load(_beside(variant, ".index.npy")), np.load(_beside(variant, ".core.npy"))
    semantic = np.full(geometry.points.shape[0], -1, np.int64)
    semantic[index[core]] = np.load(variant / "labels.npz")["semantic"][core]
    base = {name: getattr(scene, name) for name in scene.__dataclass_fields__}
    box = json.loads((alone / "report.json").read_text())["box"]
    gt = TileBundle(**base, point_index=room, halo_box=box).read_ground_truth()
    scores = _scores(geometry.points[room], semantic[room], np.full(room.size, -1), gt, vocab)
    return scores["miou"], json.loads((variant / "report.json").read_text())["num_frames"]


def _scores(points: np.ndarray, semantic: np.ndarray, instance: np.ndarray, gt: Any, vocab: Any) -> dict[str, float]:
    from panogs_core.evaluation.metrics import evaluate_ground_truth

    m = evaluate_ground_truth(points, semantic, instance, gt, vocab, modes=("standard",))["standard"]
    return {"miou": m.miou, "prq_t": m.prq_thing, "prq_s": m.prq_stuff}


def _compare_room(bundle: Path, building_run: Path, alone: Path) -> dict[str, Any]:
    from panogs_core.pipeline.run import resolve_scene_vocabulary
    from panogs_core.tiling.view import TileBundle

    scene = open_bundle(bundle)
    vocab = resolve_scene_vocabulary(scene, None)
    index = np.load(_beside(alone, ".index.npy"))
    geometry = scene.read_geometry()
    assert geometry is not None
    base = {name: getattr(scene, name) for name in scene.__dataclass_fields__}
    view = TileBundle(**base, point_index=index, halo_box=json.loads((alone / "report.json").read_text())["box"])
    gt = view.read_ground_truth()
    points = geometry.points[index]
    whole = np.load(building_run / "labels.npz")
    own = np.load(alone / "labels.npz")
    return {
        "primitives": int(index.size),
        "frames": json.loads((alone / "report.json").read_text())["num_frames"],
        "alone": _scores(points, own["semantic"], own["instance"], gt, vocab),
        "building": _scores(points, whole["semantic"][index], whole["instance"][index], gt, vocab),
    }


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--one-room":
        _room_alone(*sys.argv[2:])
        return
    if len(sys.argv) > 1 and sys.argv[1] == "--one-room-tile":
        _room_tile(*sys.argv[2:])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rooms", default="4x4")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tile-workers", type=int, default=2)
    parser.add_argument("--alone", type=int, default=4, help="rooms run alone for the per-room comparison")
    parser.add_argument(
        "--room-tile",
        action="append",
        default=[],
        metavar="HALO[,SECTION.KEY=VALUE...]",
        help="also run each of those rooms as one tile of its own (core: its rectangle, a halo of HALO m, the "
        "planner's frames), with these overrides; repeatable",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="a pipeline override for the building run and the rooms alone (its folders get a suffix); repeatable",
    )
    parser.add_argument("--root", type=Path, default=Path("/tmp/building-bench"))
    args = parser.parse_args()
    variant_suffix = "".join(f"-{kv}" for kv in args.set).replace("=", "-").replace("/", "_")
    set_args = [a for kv in args.set for a in ("--set", kv)]
    nx, ny = (int(v) for v in args.rooms.split("x"))
    bundle = args.root / f"building-{args.rooms}-seed{args.seed}"
    if not (bundle / "scene.json").is_file():
        synth_s = _cli("synth", str(bundle), "--preset", "building", "--rooms", args.rooms, "--room-preset", "large",
                       "--seed", str(args.seed))  # fmt: skip
        print(f"synth: {synth_s:.0f} s")
    run = args.root / f"run-{args.rooms}-seed{args.seed}-w{args.tile_workers}{variant_suffix}"
    if not (run / "report.json").is_file():
        wall = _cli("run", str(bundle), "--out", str(run), "--tiles", "auto", "--tile-workers", str(args.tile_workers),
                    "-q", "--set", "appearance.enabled=false", *set_args)  # fmt: skip
        children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        print(f"building run: {wall:.0f} s wall, largest process {children:.0f} MB")
    report = json.loads((run / "report.json").read_text())
    _print_building(report, json.loads((run / "metrics.json").read_text())["standard"])
    boxes = _room_boxes(bundle)
    assert len(boxes) == nx * ny, f"{len(boxes)} floors found, expected {nx * ny} rooms"
    print("\n| room | primitives | frames | mIoU alone / in the building (delta) | PRQ(T) | PRQ(S) |")
    print("|---|---:|---:|---|---|---|")
    alone_miou = {}
    for r in _spread(args.alone, nx * ny, nx):
        alone = args.root / f"alone-{args.rooms}-seed{args.seed}-room{r}{variant_suffix}"
        if not (alone / "report.json").is_file():
            subprocess.run([sys.executable, __file__, "--one-room", str(bundle), str(alone), *map(str, boxes[r]),
                            *args.set], cwd=REPO, check=True)  # fmt: skip
            doc = json.loads((alone / "report.json").read_text())
            (alone / "report.json").write_text(json.dumps({**doc, "box": list(boxes[r])}))
        row = _compare_room(bundle, run, alone)
        alone_miou[r] = row["alone"]["miou"]
        cells = [f"{row['alone'][k]:.3f} / {row['building'][k]:.3f} ({row['building'][k] - row['alone'][k]:+.3f})"
                 for k in ("miou", "prq_t", "prq_s")]  # fmt: skip
        print(f"| {r} ({r % nx}, {r // nx}) | {row['primitives']:,} | {row['frames']} | " + " | ".join(cells) + " |")
    if args.room_tile:
        print("\n| room | as one tile: halo m, overrides | frames | mIoU (alone: delta) |")
        print("|---|---|---:|---|")
    for text in args.room_tile:
        halo, *sets = text.split(",")
        for r in _spread(args.alone, nx * ny, nx):
            alone = args.root / f"alone-{args.rooms}-seed{args.seed}-room{r}{variant_suffix}"
            name = f"roomtile-{args.rooms}-seed{args.seed}-room{r}-halo{halo}" + "".join(f"-{kv}" for kv in sets)
            variant = args.root / name.replace("=", "-").replace("/", "_")
            if not (variant / "report.json").is_file():
                subprocess.run([sys.executable, __file__, "--one-room-tile", str(bundle), str(variant),
                                *map(str, boxes[r]), halo, *sets], cwd=REPO, check=True)  # fmt: skip
            miou, frames = _room_tile_miou(bundle, alone, variant)
            own = alone_miou[r]
            print(f"| {r} | {halo}, {' '.join(sets) or 'defaults'} | {frames} | {miou:.3f} ({miou - own:+.3f}) |")


def _print_building(report: dict[str, Any], metrics: dict[str, Any]) -> None:
    tiling = report["tiling"]
    tiles = tiling["tiles"]
    timings = {t["stage"]: t for t in report["stages"]}
    merge = timings.get("merge", {})
    print(f"\n{report['num_primitives']:,} primitives, {report['num_frames']} frames, {len(tiles)} tiles "
          f"(halo {tiling['halo_m']} m; {tiling['reason']})")  # fmt: skip
    for key, unit in (("core_primitives", ""), ("halo_primitives", ""), ("frames", ""), ("wall_s", " s"),
                      ("peak_rss_mb", " MB"), ("estimated_mb", " MB")):  # fmt: skip
        values = [t[key] for t in tiles]
        print(f"  tiles' {key}: {min(values):,.0f}-{max(values):,.0f}{unit} (median {np.median(values):,.0f})")
    print(f"  plan: {timings['plan']['wall_s']:.1f} s, peak {timings['plan']['peak_rss_mb']:.0f} MB; merge: "
          f"{merge.get('wall_s', 0):.1f} s, peak {merge.get('peak_rss_mb', 0):.0f} MB")  # fmt: skip
    print(f"  standard mIoU {metrics['miou']:.3f}, PRQ(T) {metrics['prq_thing']:.3f}, "
          f"PRQ(S) {metrics['prq_stuff']:.3f}; {report.get('num_instances', '?')} instances")  # fmt: skip


if __name__ == "__main__":
    main()
