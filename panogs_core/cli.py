"""The ``panogs`` command line: synth, import, validate, run, eval, query, render, and the commands of the
installed extras, found through the ``panogs.commands`` entry points (:func:`add_command_groups`).

Every command calls the same library functions as the service. Heavy modules are imported inside the commands,
so ``panogs --help`` is instant.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from importlib.metadata import Distribution, EntryPoint, PackageNotFoundError, distribution, entry_points
from pathlib import Path
from typing import Any, NoReturn, Protocol, TextIO

from panogs_core.errors import PanoGSError


def _cmd_synth(args: argparse.Namespace) -> int:
    from panogs_core.synthetic import make_building, make_scene

    if args.preset == "building":
        path = make_building(
            args.out,
            rooms=args.rooms,
            room=args.room_preset,
            difficulty=args.difficulty,
            seed=args.seed,
            feature_space=args.space,
            with_geometry=not args.no_geometry,
        )
        rooms = f"{args.rooms[0]}x{args.rooms[1]} {args.room_preset} rooms"
        print(f"wrote synthetic building ({rooms}, {args.difficulty}, seed {args.seed}) to {path}")
        return 0
    path = make_scene(
        args.out,
        preset=args.preset,
        difficulty=args.difficulty,
        seed=args.seed,
        feature_space=args.space,
        with_geometry=not args.no_geometry,
    )
    print(f"wrote synthetic scene ({args.preset}, {args.difficulty}, seed {args.seed}) to {path}")
    return 0


def _room_grid(text: str) -> tuple[int, int]:
    parts = text.split("x")
    if len(parts) in (1, 2) and all(p.isdigit() and 1 <= int(p) <= 16 for p in parts):
        return (int(parts[0]), int(parts[-1]))
    raise argparse.ArgumentTypeError(f"expected N or NxM rooms (1-16 each), got {text!r}")


def _cmd_import(args: argparse.Namespace) -> int:
    from panogs_core.language.label_sets import vocabulary_from_name_or_file

    vocabulary = (
        vocabulary_from_name_or_file(args.vocabulary, feature_space=args.feature_space) if args.vocabulary else None
    )
    common: dict[str, Any] = {
        "stride": args.stride,
        "vocabulary": vocabulary,
        "geometry": args.geometry,
        "ground_truth": args.gt,
        "feature_space": args.feature_space,
    }
    if args.layout == "scannet":
        from panogs_core.io.importers.scannet import import_scannet

        report = import_scannet(args.src, args.dst, **common)
    elif args.layout == "sevenscenes":
        from panogs_core.io.importers.sevenscenes import import_sevenscenes

        if args.geometry or args.gt:
            raise SystemExit("import sevenscenes: --geometry and --gt are not read for this layout")
        report = import_sevenscenes(
            args.src,
            args.dst,
            stride=args.stride,
            vocabulary=vocabulary,
            feature_space=args.feature_space,
            features=args.features,
            masks=args.masks,
            placeholder_maps=args.placeholder_maps,
        )
    else:
        from panogs_core.io.importers.replica import import_replica

        report = import_replica(args.src, args.dst, depth_scale=args.depth_scale, **common)
    print(report.summary())
    if args.gt:
        from panogs_core.io.ground_truth import is_scannet_annotation

        brought = " with vocabulary scannet20" if vocabulary is None and is_scannet_annotation(args.gt) else ""
        print(f"ground truth from {args.gt} written to gt/labels.npz{brought}")
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from panogs_core.io.bundle import open_bundle

    scene = open_bundle(args.bundle)
    print(
        f"{args.bundle}: valid {scene.name}: {len(scene.frames)} frames "
        f"({len(scene.feature_frames)} with features, {len(scene.mask_frames)} with masks), "
        f"camera {scene.camera.width}x{scene.camera.height}, features {scene.feature_dim}-d "
        f"{scene.feature_space}, geometry {'yes' if scene.has_geometry else 'no (TSDF)'}, "
        f"ground truth {'yes' if scene.has_ground_truth else 'no'}"
    )
    return 0


class StageReporter(Protocol):
    """Shows a run's progress: called as ``on_progress(stage, done, total)``, closed when the run ends."""

    def __call__(self, stage: str, done: int, total: int) -> None: ...

    def close(self) -> None: ...


class _Silent:
    """``--quiet``: shows nothing."""

    def __call__(self, stage: str, done: int, total: int) -> None:
        return None

    def close(self) -> None:
        return None


class StageLines:
    """One line per finished stage with its wall time, for a stream that is not a terminal.

    A log (CI, ``make demo > log``) keeps every frame of a progress bar, hundreds per stage; this writes each
    stage once, when the next one starts or the run ends.
    """

    def __init__(self, stream: TextIO, clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream
        self.clock = clock
        self.stage: str | None = None
        self.started = 0.0

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage != self.stage:
            self.close()
            self.stage, self.started = stage, self.clock()

    def close(self) -> None:
        """Write the line of the stage in progress, if any."""
        if self.stage is None:
            return
        self.stream.write(f"{self.stage:>16}: {self.clock() - self.started:.1f} s\n")
        self.stream.flush()
        self.stage = None


def stage_reporter(quiet: bool, stream: TextIO) -> StageReporter:
    """Nothing with ``--quiet``; progress bars on a terminal; one line per stage anywhere else."""
    if quiet:
        return _Silent()
    if stream.isatty():
        return _StageBars(stream)
    return StageLines(stream)


class _StageBars:
    """One tqdm bar per stage, redrawn in place (for a terminal)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.stage: str | None = None
        self.bar: Any = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if stage != self.stage:
            self.close()
            self.stage = stage
            self.bar = tqdm(
                total=max(total, 1), desc=f"{stage:>16}", unit="step", leave=True, file=self.stream, dynamic_ncols=True
            )
        if self.bar is not None:
            if total != self.bar.total:
                self.bar.total = max(total, 1)
            self.bar.n = min(done, self.bar.total)
            self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """``section.key=value`` pairs (values parsed as YAML) into a nested dict."""
    import yaml

    out: dict[str, Any] = {}
    for pair in pairs:
        if "=" not in pair:
            raise PanoGSError(f"--set {pair!r}: expected section.key=value")
        dotted, raw = pair.split("=", 1)
        node = out
        parts = dotted.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = yaml.safe_load(raw)
    return out


FITTING_LINE = "the results are written; fitting the Gaussian scene (gaussians.ply) ..."


def format_instances(instances: list[dict[str, Any]], limit: int = 40) -> str:
    """A fixed-width table of instances (things first, by class then size)."""
    rows = sorted(instances, key=lambda i: (i["kind"] != "thing", i["class_name"], -i["num_points"]))
    lines = [f"{'id':>4}  {'class':<16} {'kind':<5} {'score':>5} {'points':>7}  centroid (m)"]
    for inst in rows[:limit]:
        c = inst["centroid"]
        lines.append(
            f"{inst['id']:>4}  {inst['class_name'][:16]:<16} {inst['kind']:<5} {inst['score']:>5.2f} "
            f"{inst['num_points']:>7}  ({c[0]:6.2f}, {c[1]:6.2f}, {c[2]:6.2f})"
        )
    if len(rows) > limit:
        lines.append(f"... {len(rows) - limit} more in instances.json")
    return "\n".join(lines)


def format_appearance(summary: dict[str, Any]) -> str:
    """One line on the Gaussian scene's fit: PSNR before and after, why it did not run, or how it failed ("" without
    a fit)."""
    if summary.get("state") in ("failed", "canceled"):
        return (
            f"gaussians: the fit {summary['state']} ({summary.get('error', '')}); the results stand, gaussians.ply "
            "holds the initialisation"
        )
    if summary.get("psnr_after") is not None:
        return (
            f"gaussians: PSNR {summary['psnr_before']:.2f} -> {summary['psnr_after']:.2f} dB on "
            f"{summary['evaluated_on']} frames ({summary['iterations']} iterations)"
        )
    return f"gaussians: {summary['note']}" if summary.get("note") else ""


def format_metrics(metrics: dict[str, Any]) -> str:
    """One line per evaluation mode."""

    def num(value: Any) -> str:
        return "  n/a" if value is None else f"{value:.3f}"

    lines = []
    for mode, m in metrics.items():
        lines.append(
            f"{mode:>8}: mIoU {num(m['miou'])}  mAcc {num(m['macc'])}  "
            f"PRQ(T) {num(m['prq_thing'])}  PRQ(S) {num(m['prq_stuff'])}"
        )
    return "\n".join(lines)


def _limit_threads(requested: int | None) -> None:
    """Size torch's, OpenMP's and BLAS's pools for this run (``--threads``, default the cores this process may
    use) with idle threads sleeping instead of spinning: a busy host then slows a run by the share of the cores
    it lost, not many times more (panogs_core/threads.py). Before the pipeline's imports: the pools read the
    environment when their library loads."""
    from panogs_core.threads import apply_thread_environment, available_cores, loaded_too_early, set_torch_threads

    if loaded_too_early():  # called in a process that already runs numpy/torch (a test, a notebook): its pools
        if requested is not None:  # are its own; only an explicit --threads changes torch's count
            set_torch_threads(requested)
        return
    threads = requested if requested is not None else available_cores()
    apply_thread_environment(os.environ, threads)
    set_torch_threads(threads)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of at least 1, got {text!r}")
    return value


def _tiles_choice(text: str) -> str | tuple[int, int]:
    from panogs_core.tiling.choice import parse_tiles  # not plan.py: it loads numpy (argparse parses the default)

    try:
        return parse_tiles(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _cmd_run(args: argparse.Namespace) -> int:
    _limit_threads(args.threads)
    from panogs_core.language.label_sets import is_builtin_name, vocabulary_from_name_or_file
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import run_pipeline
    from panogs_core.types import Vocabulary

    cfg = PipelineConfig.from_yaml(Path(args.config)) if args.config else PipelineConfig()
    # The CLI's user owns the disk: a --vocabulary that is no built-in name is read here, as a file; the pipeline
    # itself takes only names and parsed vocabularies (docs/service.md, "Which request fields reach the host").
    vocabulary: str | Vocabulary | None = args.vocabulary
    if args.vocabulary is not None and not is_builtin_name(args.vocabulary):
        vocabulary = vocabulary_from_name_or_file(args.vocabulary)
    if args.set:
        cfg = cfg.with_overrides(_parse_overrides(args.set))
    progress = stage_reporter(args.quiet, sys.stderr)
    printed: list[Any] = []

    def print_results(result: Any) -> None:
        """The results as soon as they are written, before the appearance fit."""
        progress.close()
        print(
            f"\n{result.scene_name}: {result.num_primitives} primitives, {len(result.instances)} instances, "
            f"{result.total_s:.1f} s -> {result.out_dir}"
        )
        print(format_instances(result.instances))
        if result.metrics:
            print("\n" + format_metrics(result.metrics))
        if result.fit_state == "running":  # a tiled run fits none (docs/method.md §16.3)
            print("\n" + FITTING_LINE, flush=True)
        printed.append(result)

    try:
        if args.tiles == "off":
            result = run_pipeline(
                args.bundle,
                args.out,
                cfg,
                vocabulary=vocabulary,
                on_progress=progress,
                resume=not args.no_resume,
                on_results=print_results,
            )
        else:  # the plan runs a scene that fits whole as run_pipeline does (docs/method.md §16)
            from panogs_core.tiling.plan import TilingConfig
            from panogs_core.tiling.runner import run_tiled

            tiling = TilingConfig()
            if args.tile_memory_gb is not None:
                limit = args.tile_memory_gb * 1e9
                tiling = TilingConfig(memory_target_bytes=limit, whole_limit_bytes=limit)

            result = run_tiled(
                args.bundle,
                args.out,
                cfg,
                tiles=args.tiles,
                tiling=tiling,
                vocabulary=vocabulary,
                on_progress=progress,
                resume=not args.no_resume,
                on_results=print_results,
                tile_workers=args.tile_workers,
            )
    except KeyboardInterrupt:
        progress.close()
        if printed:
            print(
                "interrupted during the Gaussian fit: the results above are written, gaussians.ply holds the "
                "initialisation; run the same command again to resume the fit",
                file=sys.stderr,
            )
            return 130
        raise
    finally:
        progress.close()
    print(format_appearance(result.appearance) or "gaussians: the initialisation (no fit)")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    if args.gt:
        return _eval_against(args.run, args.gt, as_json=args.json)
    path = Path(args.run) / "metrics.json"
    if not path.is_file():
        raise PanoGSError(
            f"{path}: no metrics (the run's bundle had no gt/labels.npz, or used another vocabulary than the bundle's)"
        )
    metrics = json.loads(path.read_text())
    print(json.dumps(metrics, indent=2) if args.json else format_metrics(metrics))
    return 0


def _eval_against(run_dir: str, gt_file: str, *, as_json: bool) -> int:
    """Score a finished run against a ground-truth file (``.npz`` or ScanNet annotations)."""
    from panogs_core.evaluation.metrics import evaluate_ground_truth
    from panogs_core.io.ground_truth import load_ground_truth
    from panogs_core.io.run_folder import load_run_labels

    run = load_run_labels(run_dir)
    gt = load_ground_truth(gt_file, run.vocabulary, vertices=run.points, vertices_name="the run's primitives")
    metrics = {
        m: v.to_json()
        for m, v in evaluate_ground_truth(run.points, run.semantic, run.instance, gt, run.vocabulary).items()
    }
    if as_json:
        print(json.dumps(metrics, indent=2))
        return 0
    how = "per primitive" if gt.points is None else "each from its nearest primitive"
    print(f"{gt_file}: {len(gt.semantic)} labelled points, predictions {how} of {run_dir}")
    print(format_metrics(metrics))
    return 0


def _cmd_query(args: argparse.Namespace) -> int:
    import numpy as np

    from panogs_core.io.run_folder import load_result
    from panogs_core.language.query import query_instances
    from panogs_core.language.text_encoders import get_text_encoder

    loaded = load_result(args.run)
    query: str | np.ndarray = np.load(args.vector) if args.vector else " ".join(args.text)
    encoder = None
    if args.model_path and isinstance(query, str):
        encoder = get_text_encoder(loaded.feature_space, model_path=args.model_path)
    hits = query_instances(
        loaded.instances,
        loaded.vocabulary,
        query,
        feature_space=loaded.feature_space,
        encoder=encoder,
        top_k=args.top_k,
        min_score=args.min_score,
    )
    label = args.vector or repr(query)
    if not hits:
        print(f"query {label}: no instance scored at least {args.min_score}")
        return 0
    print(f"query {label}: {len(hits)} instance(s)")
    for hit in hits:
        lo, hi = hit.bbox_min, hit.bbox_max
        print(
            f"  instance {hit.instance_id:>4}  {hit.class_name:<16} score {hit.score:.3f}  "
            f"box [{lo[0]:.2f} {lo[1]:.2f} {lo[2]:.2f}] - [{hi[0]:.2f} {hi[1]:.2f} {hi[2]:.2f}]"
        )
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree of every command."""
    parser = _Parser(
        prog="panogs", description="Open-vocabulary 3D panoptic segmentation (PanoGS) of posed RGB-D captures."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log stage details")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("synth", help="make a synthetic scene bundle")
    p.add_argument("out", help="output bundle folder")
    p.add_argument("--preset", default="tiny", choices=["tiny", "small", "default", "large", "scan", "building"])
    p.add_argument(
        "--rooms",
        type=_room_grid,
        default=(2, 2),
        metavar="N|NxM",
        help="building only: rooms along x and y (N: N x N; default 2)",
    )
    p.add_argument(
        "--room-preset",
        default="large",
        choices=["tiny", "small", "default", "large"],
        help="building only: the kind of each room (default large)",
    )
    p.add_argument("--difficulty", default="default", choices=["easy", "default", "hard"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--space",
        default=None,
        choices=["minilm-l6", "clip-vit-b32"],
        help="feature space of the 2D features (default: the preset's; large is clip-vit-b32)",
    )
    p.add_argument("--no-geometry", action="store_true", help="omit geometry.ply (primitives by TSDF)")
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser("import", help="convert a ScanNet, Replica or 7-Scenes capture to a bundle")
    p.add_argument("layout", choices=["scannet", "replica", "sevenscenes"])
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--stride", type=int, default=1, help="keep every n-th frame")
    p.add_argument("--vocabulary", help="scannet20 | matterport21 | path to vocabulary.json")
    p.add_argument("--geometry", help="mesh or point cloud whose vertices become the primitives")
    p.add_argument("--feature-space", default="clip-vit-b32")
    p.add_argument("--depth-scale", type=float, default=6553.5, help="replica only")
    p.add_argument("--features", help="sevenscenes only: folder of <i>.npy feature maps")
    p.add_argument("--masks", help="sevenscenes only: folder of <i>.png instance masks")
    p.add_argument(
        "--placeholder-maps",
        action="store_true",
        help="sevenscenes only, without --features: a constant feature map and a one-segment mask on the first "
        "frame, enough to open the bundle for the photometric benchmark (no meaningful labels)",
    )
    p.add_argument(
        "--gt",
        metavar="FILE",
        help="ground truth for evaluation: .npz (semantic, instance[, points]) or ScanNet's "
        "<scene>_vh_clean_2.labels.ply (+ aggregation.json and segs.json beside it; vocabulary scannet20)",
    )
    p.set_defaults(func=_cmd_import)

    p = sub.add_parser("validate", help="check a bundle against the format and list every problem")
    p.add_argument("bundle")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("run", help="run the whole pipeline on a bundle")
    p.add_argument("bundle", help="bundle folder or .zip/.tar(.gz)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="YAML pipeline config (unknown keys are errors)")
    p.add_argument(
        "--set",
        action="append",
        metavar="SECTION.KEY=VALUE",
        help="override one setting, e.g. clustering.thresholds=[0.9,0.7]",
    )
    p.add_argument("--vocabulary", help="scannet20 | matterport21 | path to vocabulary.json")
    p.add_argument("--no-resume", action="store_true", help="recompute every stage")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress (bars on a terminal, else a line per stage)")
    p.add_argument(
        "--threads",
        type=_positive_int,
        metavar="N",
        help="threads of torch, OpenMP and BLAS (default: the cores this process may use)",
    )
    p.add_argument(
        "--tiles",
        type=_tiles_choice,
        default="auto",
        metavar="auto|off|NxM",
        help="split a scene into tiles and merge them: auto (the default) only when the untiled run is estimated "
        "over half this machine's memory, never (off), or into N x M tiles",
    )
    p.add_argument(
        "--tile-memory-gb",
        type=float,
        metavar="GB",
        help="with --tiles auto: the memory one run may use; a scene estimated over it is tiled, in tiles under "
        "it (default: tiles of 3 GB, for scenes over half this machine's memory; docs/method.md §16)",
    )
    p.add_argument(
        "--tile-workers",
        type=_positive_int,
        default=1,
        metavar="N",
        help="a tiled run: tiles run at once, each in a process of its own (default 1, one after another); "
        "each takes up to its tile's memory (report.json's estimated_mb)",
    )
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("eval", help="print the metrics of a run, or score it against a ground-truth file")
    p.add_argument("run", help="the --out folder of a run")
    p.add_argument(
        "--gt",
        metavar="FILE",
        help="score against this ground truth instead of the bundle's: .npz (semantic, instance[, points]) or "
        "ScanNet's <scene>_vh_clean_2.labels.ply (+ aggregation.json and segs.json beside it)",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("query", help="find instances by text or vector")
    p.add_argument("run", help="the --out folder of a run")
    p.add_argument("text", nargs="*", help="a class name or free text")
    p.add_argument("--vector", help=".npy file with one (D,) query embedding")
    p.add_argument("--top-k", type=int, default=10)
    p.add_argument("--min-score", type=float, default=0.5)
    p.add_argument("--model-path", help="text encoder folder or hub name (needed for free text in CLIP space)")
    p.set_defaults(func=_cmd_query)

    _add_render_command(sub)
    parser.not_installed = tuple(add_command_groups(sub))
    if parser.not_installed:
        parser.epilog = not_installed_text(parser.not_installed)
    return parser


def _cmd_render(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from panogs_core.errors import InputError
    from panogs_core.gaussians.views import parse_size, render_to_dir

    pose = None
    if args.pose:
        try:
            pose = json.loads(Path(args.pose).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"--pose {args.pose}: cannot read a JSON pose ({exc})") from exc
    size = parse_size(args.size) if args.size else None
    query = " ".join(args.query) if args.query else None
    written = render_to_dir(
        args.run, args.out, frame=args.frame, pose=pose, pose_where=args.pose or "pose", size=size, query=query
    )
    print(f"wrote {', '.join(sorted(written))} to {args.out}")
    return 0


def _add_render_command(sub: Any) -> None:
    """``panogs render``: PNG views of a finished run's Gaussian scene (panogs_core/gaussians/views.py)."""
    p = sub.add_parser("render", help="render a view of a run: colour, depth, semantic, instance, query relevance")
    p.add_argument("run", help="the --out folder of a run")
    view = p.add_mutually_exclusive_group(required=True)
    view.add_argument("--frame", help="a key frame id of the bundle (its pose and camera)")
    view.add_argument("--pose", metavar="FILE.json", help='{"T_world_cam": 4x4 camera-to-world[, "camera": {...}]}')
    p.add_argument("--size", metavar="WxH", help="render size (same field of view), e.g. 640x480")
    p.add_argument("--query", nargs="+", metavar="TEXT", help="also write relevance.png for this text")
    p.add_argument("--out", required=True, help="output folder for the PNGs")
    p.set_defaults(func=_cmd_render)


COMMAND_GROUP = "panogs.commands"  # entry points "<extra> = module:add_commands" (pyproject.toml)
_REQUIREMENT = re.compile(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[([^\]]*)\])?")
_EXTRA_MARKER = re.compile(r"""\bextra\s*==\s*['"]([^'"]+)['"]""")


@dataclass(frozen=True)
class MissingGroup:
    """A command group this install lacks: its entry point's name, the extra that brings it and what is missing."""

    name: str
    install: str | None  # e.g. "pip install 'panogs[service]'"; None when no extra of that name exists
    missing: tuple[str, ...]

    def describe(self) -> str:
        how = f"{self.install}; " if self.install else ""
        return f"the {self.name} commands ({how}this install lacks {', '.join(self.missing)})"


def not_installed_text(groups: Iterable[MissingGroup]) -> str:
    """One sentence naming the command groups this install lacks and how to install them."""
    return "Not installed: " + "; ".join(group.describe() for group in groups) + "."


class _Parser(argparse.ArgumentParser):
    """An unknown command also names the command groups this install lacks, with the extra that brings each."""

    not_installed: tuple[MissingGroup, ...] = ()

    def error(self, message: str) -> NoReturn:
        if self.not_installed and "invalid choice" in message:
            message = f"{message}\n{not_installed_text(self.not_installed)}"
        super().error(message)


def add_command_groups(sub: Any, groups: Iterable[EntryPoint] | None = None) -> list[MissingGroup]:
    """Add the commands of every ``panogs.commands`` entry point (default: the installed ones) to ``sub``.

    Each entry point is named for the extra its commands need (``service``, ``worker``) and names a function
    that adds them to an argparse subparsers object; the core never imports those packages itself. A group is
    skipped, and returned, when that extra's distributions are not installed or loading it misses a third-party
    module; any other error of loading it, above all an import error of our own code, is raised.
    """
    found = sorted(entry_points(group=COMMAND_GROUP) if groups is None else groups, key=lambda ep: ep.name)
    # Our packages: a module of theirs that is missing is a bug to show, not an extra to install.
    own = {"panogs_core"} | {ep.module.partition(".")[0] for ep in found}
    skipped = []
    for ep in found:
        dist: Distribution | None = getattr(ep, "dist", None)
        missing = _missing_distributions(dist, ep.name)
        if not missing:
            try:
                add = ep.load()
            except ModuleNotFoundError as exc:
                if exc.name is None or exc.name.partition(".")[0] in own:
                    raise
                missing = (exc.name,)
            else:
                add(sub)
                continue
        install = f"pip install '{dist.name}[{ep.name}]'" if dist is not None and _has_extra(dist, ep.name) else None
        skipped.append(MissingGroup(ep.name, install, missing))
    return skipped


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _extra_requirements(dist: Distribution) -> dict[str, list[tuple[str, list[str]]]]:
    """``dist``'s requirements by extra: (distribution name, its extras) per line of ``Requires-Dist``."""
    by_extra: dict[str, list[tuple[str, list[str]]]] = {}
    for line in dist.requires or ():
        spec, _, marker = line.partition(";")
        extra, name = _EXTRA_MARKER.search(marker), _REQUIREMENT.match(spec)
        if extra is not None and name is not None:
            extras = [e.strip() for e in (name[2] or "").split(",") if e.strip()]
            by_extra.setdefault(_normal(extra[1]), []).append((name[1], extras))
    return by_extra


def _has_extra(dist: Distribution, extra: str) -> bool:
    return _normal(extra) in _extra_requirements(dist)


def _missing_distributions(dist: Distribution | None, extra: str) -> tuple[str, ...]:
    """The distributions that ``extra`` of ``dist`` requires and this install lacks, through the extras of
    ``dist`` that it includes (``worker`` is ``panogs[service,pipeline]``); none when ``dist`` has no such extra."""
    if dist is None:
        return ()
    by_extra = _extra_requirements(dist)
    todo, seen, missing = [_normal(extra)], set(), set()
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        for name, extras in by_extra.get(current, ()):
            if _normal(name) == _normal(dist.name):
                todo.extend(_normal(e) for e in extras)
                continue
            try:
                distribution(name)
            except PackageNotFoundError:
                missing.add(name)
    return tuple(sorted(missing))


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``panogs``; user errors print one clear message and exit 2."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    if not sys.stderr.isatty():
        # The text encoder's own bars ("Loading weights") redraw in place too, and a log keeps every frame.
        os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
    try:
        return int(args.func(args) or 0)
    except PanoGSError as exc:
        print(f"panogs {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
