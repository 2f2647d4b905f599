"""Tiling benchmark: untiled against forced tiles on the same scenes (docs/method.md §16, docs/benchmarks.md "Tiling").

Usage:
    python bench/tiling.py [--preset large] [--seeds 0 1 2] [--tiles 2x2] [--halo 1.0] [--set SECTION.KEY=VALUE ...]
                           [--tile-workers N] [--field-seeds 0 1 2 3] [--root /tmp/tiling-bench] [--regen]

Per seed: ``panogs synth`` (kept under ``--root`` unless ``--regen``), then ``panogs run --tiles off`` and ``panogs
run --tiles NxM`` (appearance fit off in both: a tiled run fits none), each in its own process so that peak memory
is its own. ``--halo`` (metres) and ``--set`` (pipeline overrides, both runs) name variants: their run folders get a
suffix, so one root holds them side by side. Prints a markdown table: standard-mode mIoU, PRQ(T), PRQ(S) of both and
their deltas, instance counts, the share of ground-truth thing instances that cross a tile border and come out split
there (the majority predicted instance differs between two tiles' cores; the untiled run's count on the same
instances beside it, and the instances split in the tiled run alone: the ones the tiling split), the peak of the
untiled run and of every tile (the highest of its stages' sampled peaks) and their ratio, and a least-squares fit
of peak memory against primitives x frames over the runs and tiles.
``--field-seeds`` runs every pair once per seed of the language field (both runs) and adds a table of the deltas'
mean and standard deviation over them per scene seed: the field's seed alone moves one run's PRQ(T) by up to 0.1.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.io.bundle import open_bundle  # noqa: E402
from panogs_core.tiling.choice import parse_tiles  # noqa: E402
from panogs_core.tiling.plan import TilingConfig, plan_tiles  # noqa: E402

MIN_SHARE = 0.1  # an instance crosses a border when two cores each hold at least this share of its points


def _cli(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "panogs_core.cli", *args], cwd=REPO, check=True, capture_output=True)


def _run(
    bundle: Path, out: Path, tiles: str, halo: float | None = None, sets: tuple[str, ...] = (), workers: int = 1
) -> dict:
    if not (out / "report.json").is_file():
        settings = [a for kv in ("appearance.enabled=false", *sets) for a in ("--set", kv)]
        if halo is None:
            _cli("run", str(bundle), "--out", str(out), "--tiles", tiles, "--tile-workers", str(workers), "-q",
                 *settings)  # fmt: skip
        else:  # the CLI keeps the planner's halo: run the tiles through run_tiled in a process of its own
            subprocess.run([sys.executable, __file__, "--one-run", str(bundle), str(out), tiles, str(halo),
                            str(workers), *sets], cwd=REPO, check=True, capture_output=True)  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())["standard"]
    labels = np.load(out / "labels.npz")
    return {"report": report, "metrics": metrics, "instance": labels["instance"], "semantic": labels["semantic"]}


def _split_instances(owner: np.ndarray, gt_instance: np.ndarray, gt_thing: np.ndarray, pred: np.ndarray) -> tuple:
    """Of the GT thing instances whose points two tile cores each hold a share of, the ids of those the prediction
    splits there (the majority predicted instance of the two parts differs), and how many cross; returns
    (split ids, crossing)."""
    crossing, split = 0, set()
    for g in np.unique(gt_instance[gt_thing]):
        member = gt_instance == g
        cores, counts = np.unique(owner[member], return_counts=True)
        big = cores[counts >= MIN_SHARE * member.sum()]
        if big.size < 2:
            continue
        crossing += 1
        majors = set()
        for core in big:
            ids, n = np.unique(pred[member & (owner == core)], return_counts=True)
            majors.add(int(ids[np.argmax(n)]))
        if len(majors) > 1:
            split.add(int(g))
    return split, crossing


def _suffix(halo: float | None, sets: list[str], workers: int = 1) -> str:
    """The run folder's suffix of a variant: its halo, tile processes and overrides, in a file-name-safe form."""
    parts = ([] if halo is None else [f"halo{halo:g}"]) + ([] if workers == 1 else [f"w{workers}"])
    parts += [kv.replace("=", "-") for kv in sets]
    return "".join(f"-{p}" for p in parts).replace("/", "_")


SEAM_BANDS = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, np.inf))  # metres from the nearest seam


def _seam_distance(plan, points: np.ndarray, owner: np.ndarray) -> np.ndarray:  # (N,) metres, inf: no seam
    """Distance in XY from each primitive to the nearest edge of its core that is a seam (not the scene's edge)."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    out = np.full(points.shape[0], np.inf)
    for tile in plan.tiles:
        mine = owner == tile.index
        x0, x1, y0, y1 = tile.core_box
        for value, axis, edge in ((x0, 0, lo[0]), (x1, 0, hi[0]), (y0, 1, lo[1]), (y1, 1, hi[1])):
            if abs(value - edge) > plan.cell_m:
                out[mine] = np.minimum(out[mine], np.abs(points[mine, axis] - value))
    return out


def _weight_change(root: Path, plan, points: np.ndarray) -> float | None:
    """Median relative change of the fusion's confidence weight (its scene-wide ranges taken per tile) over the
    core primitives seen in both runs: |w_tile / w_untiled - 1|. None when the tiles' fusion checkpoints are gone
    (a finished tile deletes them, ``tiling/tile.py``; they were kept in the runs of docs/benchmarks.md's table)."""
    from panogs_core.tiling.tile import tile_folder

    with np.load(root["off"] / "stages" / "fusion.npz") as npz:
        whole = npz["weights"]
    changes = []
    for tile in plan.tiles:
        index, core = plan.members(tile, points)
        fused = tile_folder(root["tiled"], tile) / "stages" / "fusion.npz"
        if not fused.is_file():
            return None
        with np.load(fused) as npz:
            part = npz["weights"][core]
        ref = whole[index[core]]
        seen = (ref > 0) & (part > 0)
        changes.append(np.abs(part[seen] / ref[seen] - 1.0))
    return float(np.median(np.concatenate(changes)))


def _one_run(bundle: str, out: str, tiles: str, halo: str, workers: str, *sets: str) -> None:
    """One tiled run with a halo of ``halo`` metres (``--one-run``, in its own process)."""
    import yaml

    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.tiling.runner import run_tiled

    overrides: dict = {"appearance": {"enabled": False}}
    for kv in sets:
        key, value = kv.split("=", 1)
        section, name = key.split(".", 1)
        overrides.setdefault(section, {})[name] = yaml.safe_load(value)
    config = PipelineConfig().with_overrides(overrides)
    run_tiled(bundle, out, config, tiles=parse_tiles(tiles), tiling=TilingConfig(halo_m=float(halo)),
              tile_workers=int(workers))  # fmt: skip


def _print_field_seed_means(rows: list[dict]) -> None:
    """Per scene seed, the untiled and tiled scores and their deltas as mean ± standard deviation over the field
    seeds: one run's PRQ(T) moves by up to 0.1 with the field's seed alone (docs/benchmarks.md, "Tiling")."""
    print(
        "\n| seed | field seeds | mIoU off / tiled (delta) | PRQ(T) (delta) | PRQ(S) (delta) "
        "| split by the tiling alone |"
    )
    print("|---|---|---|---|---|---|")
    for seed in dict.fromkeys(r["seed"] for r in rows):
        mine = [r for r in rows if r["seed"] == seed]
        cells = []
        for key in ("miou", "prq_thing", "prq_stuff"):
            u = np.array([r["u"][key] for r in mine])
            t = np.array([r["t"][key] for r in mine])
            d = t - u
            cells.append(f"{u.mean():.3f} / {t.mean():.3f} ({d.mean():+.3f} ± {d.std():.3f})")
        alone = sum(len(r["split"][0] - r["split"][1]) for r in mine)
        crossing = sum(r["split"][2] for r in mine)
        print(f"| {seed} | {len(mine)} | {' | '.join(cells)} | {alone} of {crossing} |")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--one-run":
        _one_run(*sys.argv[2:])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="large")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--tiles", default="2x2")
    parser.add_argument("--halo", type=float, default=None, help="the tiled runs' halo, m (default: the planner's)")
    parser.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="a pipeline override for both runs of every seed (repeatable)",
    )
    parser.add_argument("--tile-workers", type=int, default=1, help="the tiled runs' tile processes (a process "
                        "each: a tile's peak is its own, not on top of the tiles before it)")  # fmt: skip
    parser.add_argument("--field-seeds", type=int, nargs="+", default=[0], help="run every pair once per field "
                        "seed (language_field.seed, both runs) and print the deltas' mean over them")  # fmt: skip
    parser.add_argument("--root", type=Path, default=Path("/tmp/tiling-bench"))
    parser.add_argument("--regen", action="store_true")
    args = parser.parse_args()
    rows, fit = [], []
    for seed in args.seeds:
        bundle = args.root / f"{args.preset}-{seed}"
        if args.regen or not (bundle / "scene.json").is_file():
            _cli("synth", str(bundle), "--preset", args.preset, "--seed", str(seed))
        # What the scores read of the scene (its plan takes a pass over the depth images): once per scene seed.
        scene = open_bundle(bundle)
        geometry, gt = scene.read_geometry(), scene.read_ground_truth()
        assert geometry is not None
        assert gt is not None
        assert scene.vocabulary is not None
        tiling = TilingConfig() if args.halo is None else TilingConfig(halo_m=args.halo)
        plan = plan_tiles(scene, tiling, parse_tiles(args.tiles), points=geometry.points)
        owner = plan.core_of(geometry.points)
        gt_thing = (gt.semantic >= 0) & scene.vocabulary.is_thing[np.maximum(gt.semantic, 0)]
        distance = _seam_distance(plan, geometry.points, owner)
        annotated = gt.semantic >= 0
        for field_seed in args.field_seeds:
            sets = args.sets + ([f"language_field.seed={field_seed}"] if field_seed else [])
            folders = {
                "off": args.root / f"{args.preset}-{seed}-off{_suffix(None, sets)}",
                "tiled": args.root / f"{args.preset}-{seed}-{args.tiles}{_suffix(args.halo, sets, args.tile_workers)}",
            }
            untiled = _run(bundle, folders["off"], "off", sets=tuple(sets))
            tiled = _run(bundle, folders["tiled"], args.tiles, args.halo, tuple(sets), args.tile_workers)
            split_t, crossing = _split_instances(owner, gt.instance, gt_thing, tiled["instance"])
            split_u, _ = _split_instances(owner, gt.instance, gt_thing, untiled["instance"])
            bands = []
            for a, b in SEAM_BANDS:
                band = (distance >= a) & (distance < b) & annotated
                wrong_t = tiled["semantic"][band] != gt.semantic[band]
                wrong_u = untiled["semantic"][band] != gt.semantic[band]
                bands.append((float(wrong_t.mean()), float(wrong_u.mean())))
            weight_change = _weight_change(folders, plan, geometry.points)
            u_peak = max(s["peak_rss_mb"] for s in untiled["report"]["stages"])
            tiles = tiled["report"]["tiling"]["tiles"]
            t_peaks = [t["peak_rss_mb"] for t in tiles]
            n, v = untiled["report"]["num_primitives"], untiled["report"]["num_frames"]
            fit.append((n * v, u_peak))
            fit += [((t["core_primitives"] + t["halo_primitives"]) * t["frames"], t["peak_rss_mb"]) for t in tiles]
            rows.append({
                "seed": seed, "field_seed": field_seed, "u": untiled["metrics"], "t": tiled["metrics"],
                "inst": (untiled["report"]["num_instances"], tiled["report"]["num_instances"]),
                "split": (split_t, split_u, crossing), "peak": (u_peak, t_peaks),
                "wall": (untiled["report"]["total_wall_s"], tiled["report"]["total_wall_s"]),
                "joins": tiled["report"]["tiling"]["seam_joins"], "bands": bands, "weights": weight_change,
            })  # fmt: skip
    print(
        f"| {args.preset} seed | field seed | mIoU off / {args.tiles} (delta) | PRQ(T) (delta) | PRQ(S) (delta) "
        "| instances | crossing GT instances split, tiled / untiled / by the tiling alone | seam joins "
        "| peak MB off / tiles (max ratio) | wall s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        cells = []
        for key in ("miou", "prq_thing", "prq_stuff"):
            a, b = r["u"][key], r["t"][key]
            cells.append(f"{a:.3f} / {b:.3f} ({b - a:+.3f})")
        split_t, split_u, crossing = r["split"]
        u_peak, t_peaks = r["peak"]
        peaks = ", ".join(f"{p:.0f}" for p in t_peaks)
        print(
            f"| {r['seed']} | {r['field_seed']} | {' | '.join(cells)} | {r['inst'][0]} / {r['inst'][1]} | "
            f"{len(split_t)} / {len(split_u)} / {len(split_t - split_u)} of {crossing} | {r['joins']} | "
            f"{u_peak:.0f} / {peaks} ({max(t_peaks) / u_peak:.2f}) | {r['wall'][0]:.0f} / {r['wall'][1]:.0f} |"
        )
    if len(args.field_seeds) > 1:
        _print_field_seed_means(rows)
    heads = " | ".join(f"{a:g}-{b:g} m" for a, b in SEAM_BANDS)
    print(
        f"\n| seed | field seed | wrong class, tiled / untiled, by distance to a seam: {heads} "
        "| fusion weight change (median) |"
    )
    print("|---|---|" + "---|" * len(SEAM_BANDS) + "---|")
    for r in rows:
        cells = " | ".join(f"{t:.3f} / {u:.3f}" for t, u in r["bands"])
        weights = "-" if r["weights"] is None else f"{r['weights']:.3f}"
        print(f"| {r['seed']} | {r['field_seed']} | {cells} | {weights} |")
    x, y = np.array([f[0] for f in fit], float), np.array([f[1] for f in fit], float)
    slope, intercept = np.polyfit(x, y, 1)
    print(
        f"\npeak MB = {intercept:.0f} + {slope * 2**20:.1f} bytes x primitives x frames "
        f"(least squares over {len(fit)} runs and tiles, {x.min() / 1e6:.1f}-{x.max() / 1e6:.1f} M primitive-frames)"
    )


if __name__ == "__main__":
    main()
