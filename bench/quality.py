"""Quality benchmark: mIoU, mAcc, PRQ(T), PRQ(S) over difficulties x seeds, full method and the paper's ablations.

Usage:
    python bench/quality.py [--preset small] [--difficulties easy default hard] [--seeds 0 1 2]

Prints one markdown table (mean and standard deviation over seeds, standard-mode metrics). Variants:

- full: the method as configured by default (tri-plane field, language-guided graph cut with the mask split,
  JSD affinity aggregated by weighted median, the reference's vote inside super-primitives)
- no-vote: per-primitive classes, no vote inside super-primitives
- lang-affinity: affinity from language-feature similarity instead of the SAM-mask JSD (the paper's ablation)
- no-lang-cut: graph cuts without the language criteria (the paper's ablation)
- fused-features: per-primitive fused features instead of the tri-plane field (the paper's ablation)
- no-mask-split: super-primitives the masks keep dividing are not cut in two
- mean-affinity: per-frame similarities averaged (the reference) instead of their weighted median
- depth-filter: mask ids read only where the depth residual is within 3 robust spreads of the frame's
- reference-grouping: no mask split and mean aggregation: the reference's grouping on our features

Variants run in one output folder per scene in an order that lets the stage checkpoints be reused.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.config import PipelineConfig
from panogs_core.pipeline import run_pipeline
from panogs_core.synthetic import make_scene

VARIANTS: dict[str, dict] = {
    "full": {},
    "no-vote": {"labeling": {"vote": "none"}},
    "lang-affinity": {"affinity": {"mode": "language"}},
    "no-lang-cut": {"superprimitives": {"use_language": False}},
    "fused-features": {"features_source": "fused"},
    "no-mask-split": {"superprimitives": {"split_purity": 0.0}},
    "mean-affinity": {"affinity": {"aggregate": "mean"}},
    "depth-filter": {"affinity": {"mask_depth_mad": 3.0}},
    "reference-grouping": {"superprimitives": {"split_purity": 0.0}, "affinity": {"aggregate": "mean"}},
}
METRICS = ("miou", "macc", "prq_thing", "prq_stuff")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--difficulties", nargs="+", default=["easy", "default", "hard"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--space", default="minilm-l6")
    ap.add_argument("--work", default="bench/results/quality")
    args = ap.parse_args()

    results: dict[tuple[str, str], list[dict]] = {}
    t0 = time.perf_counter()
    for difficulty in args.difficulties:
        for seed in args.seeds:
            scene_dir = Path(args.work) / f"{args.preset}-{difficulty}-{seed}"
            if not (scene_dir / "scene" / "scene.json").is_file():
                make_scene(
                    scene_dir / "scene", preset=args.preset, difficulty=difficulty, seed=seed, feature_space=args.space
                )
            for variant in args.variants:
                cfg = PipelineConfig().with_overrides(VARIANTS[variant])
                res = run_pipeline(scene_dir / "scene", scene_dir / "run", cfg)
                m = (res.metrics or {}).get("standard")
                if m is None:
                    raise SystemExit(f"{scene_dir}: no metrics (scene without ground truth?)")
                results.setdefault((difficulty, variant), []).append(m)
                print(
                    f"{difficulty:>8} seed {seed} {variant:<15} " + "  ".join(f"{k} {m[k]:.3f}" for k in METRICS),
                    file=sys.stderr,
                    flush=True,
                )

    print(
        f"\npreset {args.preset}, space {args.space}, seeds {args.seeds}, standard mode "
        f"(mean ± std over seeds); {time.perf_counter() - t0:.0f} s\n"
    )
    print("| difficulty | variant | " + " | ".join(METRICS) + " |")
    print("|---|---|" + "---|" * len(METRICS))
    for difficulty in args.difficulties:
        for variant in args.variants:
            rows = results[(difficulty, variant)]
            cells = []
            for k in METRICS:
                vals = [r[k] for r in rows]
                sd = statistics.pstdev(vals) if len(vals) > 1 else 0.0
                cells.append(f"{statistics.mean(vals):.3f} ± {sd:.3f}")
            print(f"| {difficulty} | {variant} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
