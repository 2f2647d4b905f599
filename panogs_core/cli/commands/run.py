"""``panogs run``: the whole pipeline on a bundle, whole or as tiles; the results printed as soon as they are
written, before the appearance fit.

The thread pools are sized first (:func:`~panogs_core.cli.arguments.limit_threads`): parsing this command's
arguments imports nothing numeric, and the pipeline's modules are imported only after.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from panogs_core.cli.arguments import VOCABULARY_HELP, limit_threads, parse_overrides, positive_int, tiles_choice
from panogs_core.cli.display import FITTING_LINE, format_appearance, format_instances, format_metrics, stage_reporter

if TYPE_CHECKING:
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.types import Vocabulary


def add_command(sub: Any) -> None:
    """Add ``run`` to an argparse subparsers object."""
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
    p.add_argument("--vocabulary", help=VOCABULARY_HELP)
    p.add_argument("--no-resume", action="store_true", help="recompute every stage")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress (bars on a terminal, else a line per stage)")
    p.add_argument(
        "--threads",
        type=positive_int,
        metavar="N",
        help="threads of torch, OpenMP and BLAS (default: the cores this process may use)",
    )
    p.add_argument(
        "--tiles",
        type=tiles_choice,
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
        type=positive_int,
        default=1,
        metavar="N",
        help="a tiled run: tiles run at once, each in a process of its own (default 1, one after another); "
        "each takes up to its tile's memory (report.json's estimated_mb)",
    )
    p.add_argument(
        "--masks-model",
        metavar="PATH_OR_HUB",
        help="a Segment Anything model (folder or hub name, e.g. Zigeng/SlimSAM-uniform-77) that computes the "
        "masks of a bundle that has none, from its colour frames (docs/method.md §17); its prompt grid is "
        "maps2d.points_per_side, by default 8 x 8 on a CPU and 32 x 32 on a GPU",
    )
    p.add_argument(
        "--features-model",
        metavar="PATH_OR_HUB",
        help="a CLIP model (folder or hub name, e.g. openai/clip-vit-base-patch16) that computes the feature maps "
        "of a bundle that has none; its text tower embeds the label set (query the run with --model-path it)",
    )
    p.add_argument(
        "--allow-download",
        action="store_true",
        help="let a hub name missing from the local Hugging Face cache be downloaded (never a folder)",
    )
    p.set_defaults(func=run_run)


def run_run(args: argparse.Namespace) -> int:
    """Run the pipeline (or the tiled run), printing the results before the fit; 130 on a Ctrl-C during the fit."""
    limit_threads(args.threads)
    cfg, vocabulary = _settings(args)
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
        result = _runner(args)(
            args.bundle,
            args.out,
            cfg,
            vocabulary=vocabulary,
            on_progress=progress,
            resume=not args.no_resume,
            on_results=print_results,
            map_models=_map_models(args),
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


def _settings(args: argparse.Namespace) -> tuple[PipelineConfig, str | Vocabulary | None]:
    """The pipeline config (``--config``, then ``--set``) and the vocabulary: a built-in name, or a file read."""
    from panogs_core.language.label_sets import is_builtin_name, vocabulary_from_name_or_file
    from panogs_core.pipeline.config import PipelineConfig

    cfg = PipelineConfig.from_yaml(Path(args.config)) if args.config else PipelineConfig()
    # The CLI's user owns the disk: a --vocabulary that is no built-in name is read here, as a file; the pipeline
    # itself takes only names and parsed vocabularies (docs/service.md, "Which request fields reach the host").
    vocabulary: str | Vocabulary | None = args.vocabulary
    if args.vocabulary is not None and not is_builtin_name(args.vocabulary):
        vocabulary = vocabulary_from_name_or_file(args.vocabulary)
    overrides = parse_overrides(args.set) if args.set else {}
    if overrides:
        cfg = cfg.with_overrides(overrides)
    return cfg, vocabulary


def _map_models(args: argparse.Namespace) -> Any:
    """The models that compute the maps a bundle lacks (None when none is named)."""
    if not (args.masks_model or args.features_model):
        return None
    from panogs_core.stages.maps2d import MapModels

    return MapModels(masks=args.masks_model, features=args.features_model, allow_download=args.allow_download)


def _runner(args: argparse.Namespace) -> Callable[..., Any]:
    """``run_pipeline`` with ``--tiles off``; otherwise the tiled run, whose plan runs a scene that fits whole as
    ``run_pipeline`` does (docs/method.md §16)."""
    if args.tiles == "off":
        from panogs_core.pipeline.run import run_pipeline

        return run_pipeline
    from functools import partial

    from panogs_core.tiling.plan import TilingConfig
    from panogs_core.tiling.runner import run_tiled

    tiling = TilingConfig()
    if args.tile_memory_gb is not None:
        limit = args.tile_memory_gb * 1e9
        tiling = TilingConfig(memory_target_bytes=limit, whole_limit_bytes=limit)
    return partial(run_tiled, tiles=args.tiles, tiling=tiling, tile_workers=args.tile_workers)
