"""When a run's results are ready, against when the whole run (the appearance fit last) has ended.

Usage:
    python bench/results_first.py BUNDLE [--out DIR] [--threads 1] [--fit-off]

Runs ``run_pipeline`` once with the default settings and no checkpoints, and prints one JSON line: the seconds
until ``on_results`` was called (the labels, instances and point views written), the seconds of the whole run,
the fit's own time, the primitive count and the fit's state, iterations and PSNR before and after
(docs/gaussians.md, "Results before the fit"). ``--fit-off`` runs the same with ``appearance.enabled: false``,
the time to results that the default run's must match.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from typing import Any

from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.run import PipelineResult, run_pipeline
from panogs_core.threads import set_torch_threads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bundle")
    parser.add_argument("--out", help="the run folder (default: a temporary folder)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--fit-off", action="store_true", help="appearance.enabled: false (the baseline)")
    args = parser.parse_args()
    set_torch_threads(args.threads)
    out = args.out or tempfile.mkdtemp(prefix="results-first-")
    marks: dict[str, Any] = {}
    start = time.perf_counter()

    def on_results(_: PipelineResult) -> None:
        marks["results_s"] = round(time.perf_counter() - start, 2)

    cfg = PipelineConfig().with_overrides({"appearance": {"enabled": False}} if args.fit_off else None)
    result = run_pipeline(args.bundle, out, cfg, resume=False, on_results=on_results)
    marks["total_s"] = round(time.perf_counter() - start, 2)
    marks["fit_s"] = next(round(t.wall_s, 2) for t in result.timings if t.name == "appearance")
    marks["primitives"] = result.num_primitives
    marks["fit"] = {k: result.appearance.get(k) for k in ("state", "iterations", "psnr_before", "psnr_after")}
    print(json.dumps(marks))


if __name__ == "__main__":
    main()
