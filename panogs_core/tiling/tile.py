"""One tile of a tiled run: its stages 1-8 by :func:`run_pipeline` on the tile's view of the bundle, in its own run
folder under ``tiles/`` (docs/method.md §16). Used by the one-process runner (:mod:`runner`), the tile processes
(:mod:`parallel`) and the service's tile tasks (``worker/tiles.py``).
"""

from __future__ import annotations

import gc
import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.heap import return_freed_heap
from panogs_core.io.bundle import Bundle
from panogs_core.io.run_folder import LABELS_NPZ, REPORT_JSON, STAGES_FOLDER, TILES_FOLDER
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.input_hash import hash_bundle
from panogs_core.pipeline.profiling import StageStats
from panogs_core.pipeline.result import StageProgressFn
from panogs_core.pipeline.run import run_pipeline
from panogs_core.stages.maps2d.stage import maps_key
from panogs_core.tiling.plan import TilePlan, TileSpec
from panogs_core.tiling.view import tile_bundle
from panogs_core.types import Vocabulary

log = logging.getLogger(__name__)


def plan_path(out: Path) -> Path:
    """The plan of a tiled run, beside its tiles' folders."""
    return TILES_FOLDER.path(out) / "plan.json"


def tile_folder(out: Path, tile: TileSpec) -> Path:
    """The run folder of one tile."""
    return TILES_FOLDER.path(out) / tile.name


# A finished tile keeps what the merge and a resumed run read (labels, instances and their features, the
# primitives' checkpoint); its other checkpoints go: the fusion's and the field's (N, D) features are about 0.45 GB
# a tile of 80k primitives, some 40 GB for the 4 x 4 building's 77-94 tiles (docs/benchmarks.md).
_KEPT_CHECKPOINTS = frozenset({"primitives", "superprimitives", "clustering", "labeling"})
_TILE_DONE = "tile.json"  # in a tile's folder: its report row and timing, with the key they were made under


def run_tile(
    scene: Bundle,
    plan: TilePlan,
    tile: TileSpec,
    points: np.ndarray,
    cfg: PipelineConfig,
    vocab: Vocabulary,
    out: Path,
    on_progress: StageProgressFn | None,
    resume: bool,
    scene_hash: str | None = None,
) -> tuple[dict[str, Any], StageStats]:
    """Run one tile's stages 1-8 in its own folder; its report row and its timing.

    A tile finished before under the same inputs, settings and vocabulary (``tile.json``) is not run again; a
    finished tile's bulky checkpoints are removed (``_KEPT_CHECKPOINTS``). ``scene_hash``: the scene's bundle hash,
    when known: the tile's is made from it (:func:`tile_input_hash`) instead of reading the tile's files to hash
    them (about 1 GB a tile of the design's building, its frames read again by every tile that shares them)."""
    view, core = tile_bundle(scene, plan, tile, points)
    folder = tile_folder(out, tile)
    label = f"tile {tile.index + 1}/{len(plan.tiles)}"
    view_hash = None if scene_hash is None else tile_input_hash(scene_hash, plan, tile)
    done = _finished_tile(folder, view, cfg, vocab, view_hash) if resume else None
    if done is not None:
        log.info("%s: finished before, kept", label)
        return done

    def progress(stage: str, done: int, total: int) -> None:
        if on_progress is not None:
            on_progress(f"{label} {stage}", done, total)

    start = time.perf_counter()
    result = run_pipeline(
        view, folder, cfg, vocabulary=vocab, on_progress=progress, resume=resume, input_hash=view_hash
    )
    wall = time.perf_counter() - start
    # Peak of the tile: the highest of its stages' sampled peaks (the process's lifetime peak would carry the
    # tiles before it).
    peak = max((t.peak_rss_mb for t in result.timings), default=0.0)
    row = {
        **tile.to_json(),
        "core_primitives": int(core.sum()),
        "halo_primitives": int(core.size - core.sum()),
        "instances": len(result.instances),
        "unseen_primitives": result.unseen,
        "wall_s": round(wall, 3),
        "peak_rss_mb": round(peak, 1),
    }
    log.info("%s: %d + %d primitives, %d frames, %.1f s, peak %.0f MB", label, row["core_primitives"],
             row["halo_primitives"], len(tile.frame_ids), wall, peak)  # fmt: skip
    stats = StageStats(name=f"tile {tile.index}", wall_s=wall, peak_rss_mb=peak)
    _drop_bulky_checkpoints(folder)
    input_hash = json.loads(REPORT_JSON.path(folder).read_text())["input_sha256"]
    doc = {"key": _tile_key(input_hash, cfg, vocab, maps_key(view)), "row": row, "wall_s": wall, "peak_rss_mb": peak}
    (folder / _TILE_DONE).write_text(json.dumps(doc))
    return row, stats


def tile_input_hash(scene_hash: str, plan: TilePlan, tile: TileSpec) -> str:
    """A tile's input hash made from its scene's: the scene's bytes and where the tile lies (its name digests its
    cells, halo box and frames; the plan's grid places the cells) decide every byte the tile's run reads."""
    grid = [[float(v) for v in plan.origin], float(plan.cell_m), int(plan.halo_cells)]
    text = json.dumps(["tile:v1", scene_hash, tile.name, grid])
    return hashlib.sha256(text.encode()).hexdigest()


def _tile_key(input_hash: str, cfg: PipelineConfig, vocab: Vocabulary, maps: str) -> str:
    """``maps``: the computed maps' key (stages/maps2d/stage.py), which the bundle's hash does not cover."""
    text = json.dumps([input_hash, cfg.to_dict(), list(vocab.names), [bool(t) for t in vocab.is_thing], maps])
    return hashlib.sha256(text.encode()).hexdigest()


def _finished_tile(
    folder: Path, view: Bundle, cfg: PipelineConfig, vocab: Vocabulary, view_hash: str | None
) -> tuple[dict[str, Any], StageStats] | None:
    """The row and timing of a tile finished under the same key, else None (``view_hash``: the tile's input hash
    when known, else the tile's files hashed again)."""
    path = folder / _TILE_DONE
    if not path.is_file() or not LABELS_NPZ.path(folder).is_file():
        return None
    doc = json.loads(path.read_text())
    if doc.get("key") != _tile_key(view_hash or hash_bundle(view), cfg, vocab, maps_key(view)):
        return None
    index = doc["row"]["index"]
    return doc["row"], StageStats(name=f"tile {index}", wall_s=doc["wall_s"], peak_rss_mb=doc["peak_rss_mb"])


def _drop_bulky_checkpoints(folder: Path) -> None:
    from panogs_core.stages.primitives import Primitives

    stages = STAGES_FOLDER.path(folder)
    kept = set(_KEPT_CHECKPOINTS)
    if Primitives.load(stages / "primitives.npz").colors is None:
        kept.add("fusion")  # the merge takes the primitives' colours from the fusion then (_scene_primitives)
    for path in stages.glob("*.npz"):
        if path.stem not in kept:
            path.unlink()


def release_memory() -> None:
    """Hand what the last tile freed back to the system, so the next tile's peak is its own: the garbage
    collector for cycles, then glibc's ``malloc_trim`` for the freed heap it keeps (a no-op elsewhere)."""
    gc.collect()
    return_freed_heap()
