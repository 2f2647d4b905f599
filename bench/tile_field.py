"""The language field of a tile against the room's: how well each decodes the true class, per field seed.

Usage:
    python bench/tile_field.py BUNDLE RUN [--tiles 2x2] [--field-seeds 0 1 2] [--field-halo M]
                               [--set KEY=VALUE ...]

``RUN`` is an untiled run of ``BUNDLE`` (``panogs run --tiles off``): its fusion checkpoint gives the targets of
every field fitted here, so the tiles' fields see the room's fused features and weights exactly, and only the
field's training set differs. Per field seed it fits the field over the whole room and, per tile of the plan
(``--tiles``, the planner's halo), over the tile's primitives (core and halo, or the core grown by
``--field-halo`` metres), and prints the share of annotated primitives whose decoded feature's nearest class
text is the ground-truth class, over the tiles' cores, for primitives some key frame saw and for those none saw
(the field's extrapolation), with the mean cosine of the decoded features to the fused ones (seen primitives).
``--set`` overrides ``LanguageFieldConfig`` for every fit (``epochs=5``; JSON values). docs/benchmarks.md,
"Tiling", reads the table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.io.bundle import open_bundle  # noqa: E402
from panogs_core.stages.fusion import FusedFeatures  # noqa: E402
from panogs_core.stages.language_field import fit_language_field  # noqa: E402
from panogs_core.stages.language_field.config import LanguageFieldConfig  # noqa: E402
from panogs_core.tiling.choice import parse_tiles  # noqa: E402
from panogs_core.tiling.plan import TilingConfig, plan_tiles  # noqa: E402


def _decoded_classes(points: np.ndarray, fused: FusedFeatures, text: np.ndarray, cfg: LanguageFieldConfig) -> tuple:
    """Fit a field on the points; the nearest class of each decoded feature and the decoded features."""
    decoded = fit_language_field(points, fused, cfg).features  # (n, D) unit rows
    return np.argmax(decoded @ text.T, axis=1), decoded


def _scores(
    pred: np.ndarray, decoded: np.ndarray, truth: np.ndarray, unit_targets: np.ndarray, seen: np.ndarray
) -> str:
    """Right-class shares on seen and unseen annotated primitives, and the mean cosine to the (unit) fused rows of
    the seen ones."""
    annotated = truth >= 0
    right = pred == truth
    cosine = float((decoded[seen] * unit_targets).sum(axis=1).mean())
    return f"{right[annotated & seen].mean():.4f} | {right[annotated & ~seen].mean():.4f} | {cosine:.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bundle", type=Path)
    parser.add_argument("run", type=Path, help="an untiled run of the bundle (its stages/fusion.npz)")
    parser.add_argument("--tiles", default="2x2")
    parser.add_argument("--field-seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--field-halo", type=float, default=None, help="metres around a core the tile's field "
                        "trains on (default: the tile's own halo)")  # fmt: skip
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    scene = open_bundle(args.bundle)
    geometry, truth, vocabulary = scene.read_geometry(), scene.read_ground_truth(), scene.vocabulary
    assert geometry is not None
    assert truth is not None
    assert vocabulary is not None
    assert vocabulary.embeddings is not None
    text = vocabulary.embeddings / np.linalg.norm(vocabulary.embeddings, axis=1, keepdims=True)
    fused = FusedFeatures.load(args.run / "stages" / "fusion.npz")
    seen = fused.weights > 0
    unit_targets = fused.features[seen] / np.linalg.norm(fused.features[seen], axis=1, keepdims=True)
    points = geometry.points
    plan = plan_tiles(scene, TilingConfig(), parse_tiles(args.tiles), points=points)
    wide = plan if args.field_halo is None else plan_tiles(
        scene, TilingConfig(halo_m=args.field_halo), parse_tiles(args.tiles), points=points
    )  # fmt: skip
    overrides = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.sets)}
    owner = plan.core_of(points)
    print("| field seed | field | seen: right class | unseen: right class | cosine to fused |")
    print("|---|---|---|---|---|")
    for seed in args.field_seeds:
        cfg = dataclasses.replace(LanguageFieldConfig(), seed=seed, **overrides)
        room_pred, room_decoded = _decoded_classes(points, fused, text, cfg)
        tiled_pred, tiled_decoded = np.empty_like(room_pred), np.empty_like(room_decoded)
        for tile in wide.tiles:
            index, core = wide.members(tile, points)
            assert (owner[index[core]] == tile.index).all()  # the same cores whatever the field's halo
            part = dataclasses.replace(fused, features=fused.features[index], weights=fused.weights[index],
                                       seen_count=fused.seen_count[index], colors=None)  # fmt: skip
            pred, decoded = _decoded_classes(points[index], part, text, cfg)
            tiled_pred[index[core]], tiled_decoded[index[core]] = pred[core], decoded[core]
        for name, pred, decoded in (("room", room_pred, room_decoded), ("tiles", tiled_pred, tiled_decoded)):
            print(f"| {seed} | {name} | {_scores(pred, decoded, truth.semantic, unit_targets, seen)} |", flush=True)


if __name__ == "__main__":
    main()
