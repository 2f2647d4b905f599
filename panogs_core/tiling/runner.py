"""``run_tiled``: plan, run every tile with :func:`run_pipeline`, merge, write the scene's files (docs/method.md §16).

One process runs the tiles one after another, or ``tile_workers`` processes of this machine side by side
(:mod:`panogs_core.tiling.parallel`); the service runs them as sub-jobs on its workers (docs/service.md). A
scene that the plan leaves whole goes straight to :func:`run_pipeline`, so its files are an untiled run's,
byte for byte. A tiled run's folder holds the scene's files (docs/architecture.md, "Outputs of a run"), each tile's
own run folder under ``tiles/<tile name>/`` (its checkpoints: a re-run resumes tile by tile) and ``report.json``
with the plan and, per tile, its core and halo primitives, frames, wall time and peak memory.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.bundle import Bundle, open_bundle
from panogs_core.io.run_folder import BUNDLE_FOLDER, STAGES_FOLDER, TILES_FOLDER
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.input_hash import hash_bundle
from panogs_core.pipeline.profiling import StageStats, StageTimer
from panogs_core.pipeline.report import stage_rows
from panogs_core.pipeline.report import write_report as write_run_report
from panogs_core.pipeline.result import FIT_SKIPPED, PipelineResult, ResultsFn, StageProgressFn
from panogs_core.pipeline.run import run_pipeline
from panogs_core.pipeline.stage_table import resolve_scene_vocabulary
from panogs_core.stages.maps2d import MapModels
from panogs_core.stages.maps2d.stage import forget_maps, missing_kinds, with_computed_maps
from panogs_core.tiling.choice import TILES_AUTO, TILES_OFF
from panogs_core.tiling.merge import TileLabels, merge_tiles
from panogs_core.tiling.plan import TilePlan, TilingConfig, plan_tiles
from panogs_core.tiling.tile import plan_path, release_memory, run_tile, tile_folder
from panogs_core.types import Vocabulary

log = logging.getLogger(__name__)

# DEPARTURE (docs/method.md §16.3): a tiled run fits no Gaussian scene; gaussians.ply is the initialisation.
_NO_FIT_NOTE = "tiled run: the appearance fit does not run per tile; gaussians.ply holds the initialisation"


def run_tiled(
    bundle: str | Path | Bundle,
    out_dir: str | Path,
    config: PipelineConfig | None = None,
    *,
    tiles: str | tuple[int, int] = TILES_AUTO,
    tiling: TilingConfig | None = None,
    vocabulary: str | Vocabulary | None = None,
    on_progress: StageProgressFn | None = None,
    resume: bool = True,
    on_results: ResultsFn | None = None,
    tile_workers: int = 1,
    map_models: MapModels | None = None,
) -> PipelineResult:
    """Run a scene as tiles and merge them; a scene the plan leaves whole runs as :func:`run_pipeline` does.

    Args:
        bundle, out_dir, config, vocabulary, on_progress, resume, on_results, map_models: as
            :func:`run_pipeline`. The 2D maps a bundle lacks are computed once for the whole scene, before the
            plan (stage ``maps_2d``), and every tile reads them.
            Progress names the stages ``plan``, ``tile <k>/<K> <stage>`` and ``merge``.
        tiles: ``auto``, ``off`` or ``(nx, ny)`` (``panogs_core.tiling.choice.parse_tiles``).
        tiling: Planner settings (memory target, halo).
        tile_workers: Tiles run at once, each in a process of its own (1: one after another, in this process).

    Raises:
        InputError: tiles were forced on a bundle without geometry.
        BundleError, Cancelled: as :func:`run_pipeline`.
    """
    cfg = config or PipelineConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    if not resume:
        forget_maps(STAGES_FOLDER.path(out))
    scene = bundle if isinstance(bundle, Bundle) else open_bundle(bundle, workdir=BUNDLE_FOLDER.path(out))
    plan, points, plan_stats = plan_run(scene, cfg, tiles, tiling, on_progress)
    maps_stats = None
    if plan.tiled and missing_kinds(scene):
        # A tile's frames are those with maps: plan again once they are computed, for the whole scene at once.
        scene, maps_stats = _maps(scene, out, cfg, map_models, on_progress)
        plan, points, plan_stats = plan_run(scene, cfg, tiles, tiling, on_progress)
    if not plan.tiled:
        return run_pipeline(scene, out, cfg, vocabulary=vocabulary, on_progress=on_progress, resume=resume,
                            on_results=on_results, map_models=map_models)  # fmt: skip
    assert points is not None
    vocab = resolve_scene_vocabulary(scene, vocabulary, map_models)
    TILES_FOLDER.path(out).mkdir(parents=True, exist_ok=True)
    plan.save(plan_path(out))
    tile_cfg = tile_config(cfg)
    if tile_workers > 1 and len(plan.tiles) > 1 and scene.computed is None:  # a process reopens the bundle's files
        from panogs_core.tiling.parallel import run_tiles_in_processes

        done = run_tiles_in_processes(scene.root, out, plan, tile_cfg, vocab, workers=tile_workers, resume=resume,
                                      on_progress=on_progress)  # fmt: skip
    else:
        done = []
        for tile in plan.tiles:
            done.append(run_tile(scene, plan, tile, points, tile_cfg, vocab, out, on_progress, resume))
            release_memory()
    tile_rows = [row for row, _ in done]
    timings = [*([maps_stats] if maps_stats else []), plan_stats, *(stats for _, stats in done)]
    result, seam_joins = merge_run(scene, plan, points, vocab, out, timings, on_progress)
    result.total_s = time.perf_counter() - t_start
    # The results first, as an untiled run's: their report has no bundle hash (it reads every file of the bundle,
    # 9.4 GB for the design's building); the last report, after them, has it.
    write_report(out, scene, cfg, vocabulary, plan, tile_rows, seam_joins, result, input_hash=None)
    if on_results is not None:
        on_results(result)
    write_report(out, scene, cfg, vocabulary, plan, tile_rows, seam_joins, result, input_hash=hash_bundle(scene))
    return result


def _maps(
    scene: Bundle, out: Path, cfg: PipelineConfig, models: MapModels | None, on_progress: StageProgressFn | None
) -> tuple[Bundle, StageStats]:
    """The scene with the 2D maps it lacks computed (stage ``maps_2d``, timed)."""
    with StageTimer("maps_2d") as timer:
        scene = with_computed_maps(
            scene, STAGES_FOLDER.path(out), cfg.maps2d, models, _named(on_progress, "maps_2d"),
            on_reused=lambda: setattr(timer.stats, "cached", True),
        )  # fmt: skip
    return scene, timer.stats


def plan_run(
    scene: Bundle,
    cfg: PipelineConfig,
    tiles: str | tuple[int, int],
    tiling: TilingConfig | None,
    on_progress: StageProgressFn | None,
) -> tuple[TilePlan, np.ndarray | None, StageStats]:
    """The plan of a run (bounded memory, no feature map read), the scene's primitive points (None without
    geometry) and the plan's timing.

    Raises:
        InputError: tiles were forced on a bundle without geometry.
    """
    geometry = scene.read_geometry() if cfg.primitives.use_geometry else None
    if geometry is None and tiles not in (TILES_AUTO, TILES_OFF):
        raise InputError("--tiles NxM needs geometry.ply (and primitives.use_geometry): the TSDF path's primitives "
                         "exist only after stage 1")  # fmt: skip
    points = None if geometry is None else geometry.points
    del geometry
    with StageTimer("plan") as timer:
        plan = plan_tiles(scene, tiling or TilingConfig(), tiles if points is not None else TILES_OFF, points=points,
                          on_progress=_named(on_progress, "plan"))  # fmt: skip
    log.info("tiling plan: %s, %d tile(s)", plan.reason, len(plan.tiles))
    return plan, points, timer.stats


def tile_config(cfg: PipelineConfig) -> PipelineConfig:
    """The config each tile runs with: the run's, without the appearance fit (docs/method.md §16.3)."""
    return cfg.with_overrides({"appearance": {"enabled": False}})


def merge_run(
    scene: Bundle,
    plan: TilePlan,
    points: np.ndarray,
    vocab: Vocabulary,
    out: Path,
    timings: list[StageStats],
    on_progress: StageProgressFn | None,
) -> tuple[PipelineResult, int]:
    """Merge the finished tiles under ``out`` (``tiles/<tile name>/``) into the scene's files; the result, with
    ``timings`` and the merge's own as its timings, and the number of seam joins. ``report.json`` is the
    caller's (:func:`write_report`), once it knows the run's whole wall time."""
    with StageTimer("merge") as timer:
        result, seam_joins = _merge(scene, plan, points, vocab, out, on_progress)
    result.timings = [*timings, timer.stats]
    result.appearance = {"state": FIT_SKIPPED, "fitted": False, "note": _NO_FIT_NOTE}
    return result, seam_joins


def _named(sink: StageProgressFn | None, stage: str) -> Any:
    if sink is None:
        return None
    return lambda done, total: sink(stage, done, total)


def _tile_labels(out: Path, plan: TilePlan, points: np.ndarray) -> Iterator[TileLabels]:
    for tile in plan.tiles:
        index, core = plan.members(tile, points)
        yield TileLabels.from_run(tile_folder(out, tile), index, core)


def _merge(
    scene: Bundle,
    plan: TilePlan,
    points: np.ndarray,
    vocab: Vocabulary,
    out: Path,
    on_progress: StageProgressFn | None,
) -> tuple[PipelineResult, int]:
    """Merge the tiles' labels and write the scene's files with the exporter of an untiled run; the result and
    the number of seam joins."""
    from panogs_core.stages.clustering import Clusters
    from panogs_core.stages.export import write_outputs
    from panogs_core.stages.superprimitives import SuperPrimitives

    if on_progress is not None:
        on_progress("merge", 0, 1)
    merged = merge_tiles(_tile_labels(out, plan, points), points, vocab)
    prims, fused = _scene_primitives(out, plan, points)
    files, metrics = write_outputs(
        out, scene, prims, fused, SuperPrimitives(labels=merged.superprimitive),
        Clusters(labels=merged.cluster), merged.labels, vocab, gaussians=None,
    )  # fmt: skip
    log.info("merge: %d instances, %d seam joins", len(merged.labels.instances), merged.seam_joins)
    if on_progress is not None:
        on_progress("merge", 1, 1)
    result = PipelineResult(
        out_dir=out,
        scene_name=scene.name,
        num_primitives=int(points.shape[0]),
        instances=[i.to_json() for i in merged.labels.instances],
        timings=[],
        metrics=metrics,
        files=files,
    )
    return result, merged.seam_joins


def _scene_primitives(out: Path, plan: TilePlan, points: np.ndarray) -> tuple[Any, Any]:
    """The scene's primitives (normals, scales, colours) gathered from the tiles' cores, and a fused-features
    stand-in that carries only what the exporter reads of it (no colours: the primitives have them)."""
    from panogs_core.stages.fusion import FusedFeatures
    from panogs_core.stages.primitives import Primitives

    n = points.shape[0]
    normals = np.zeros((n, 3), np.float32)
    scales = np.zeros((n, 3), np.float32)
    opacities = np.zeros(n, np.float32)
    colors = np.full((n, 3), 0.5, np.float32)
    for tile in plan.tiles:
        index, core = plan.members(tile, points)
        stages = STAGES_FOLDER.path(tile_folder(out, tile))
        tile_prims = Primitives.load(stages / "primitives.npz")
        own = index[core]
        normals[own], scales[own], opacities[own] = (tile_prims.normals[core], tile_prims.scales[core],
                                                     tile_prims.opacities[core])  # fmt: skip
        if tile_prims.colors is not None:
            colors[own] = tile_prims.colors[core]
        else:  # the colours fused from the frames: one array of the fusion's checkpoint, read alone
            with np.load(stages / "fusion.npz", allow_pickle=False) as npz:
                if "colors" in npz.files:
                    colors[own] = npz["colors"][core]
    prims = Primitives(points=np.asarray(points, np.float32), normals=normals, colors=colors, scales=scales,
                       opacities=opacities, source="geometry")  # fmt: skip
    fused = FusedFeatures(
        features=np.zeros((n, 0), np.float32), weights=np.zeros(n, np.float32), seen_count=np.zeros(n, np.int32),
        colors=None,
    )  # fmt: skip
    return prims, fused


def write_report(
    out: Path,
    scene: Bundle,
    cfg: PipelineConfig,
    vocabulary_spec: str | Vocabulary | None,
    plan: TilePlan,
    tile_rows: list[dict[str, Any]],
    seam_joins: int,
    result: PipelineResult,
    *,
    input_hash: str | None,
) -> None:
    """``report.json`` of a tiled run: an untiled run's fields (every stage on the CPU: the fit does not run), with
    ``tiling`` (the plan and every tile). ``input_hash``: the bundle's (:func:`hash_bundle`, or one the caller
    knows), None while it is not known."""
    tiling = {**plan.to_json(), "tiles": tile_rows, "seam_joins": seam_joins}
    write_run_report(out, scene, cfg, vocabulary_spec, input_hash, result, stage_rows(result.timings),
                     tiling=tiling)  # fmt: skip
