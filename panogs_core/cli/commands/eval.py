"""``panogs eval``: the metrics of a finished run (its ``metrics.json``), or its score against a ground-truth file
(``.npz`` or ScanNet's annotations) without re-running it."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from panogs_core.cli.display import format_metrics
from panogs_core.errors import PanoGSError


def add_command(sub: Any) -> None:
    """Add ``eval`` to an argparse subparsers object."""
    p = sub.add_parser("eval", help="print the metrics of a run, or score it against a ground-truth file")
    p.add_argument("run", help="the --out folder of a run")
    p.add_argument(
        "--gt",
        metavar="FILE",
        help="score against this ground truth instead of the bundle's: .npz (semantic, instance[, points]) or "
        "ScanNet's <scene>_vh_clean_2.labels.ply (+ aggregation.json and segs.json beside it)",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_eval)


def run_eval(args: argparse.Namespace) -> int:
    """Print ``metrics.json`` (a table, or the JSON with ``--json``), or score against ``--gt``."""
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
