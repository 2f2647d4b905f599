"""The cost of one appearance-fit snapshot (panogs_core.snapshots): seconds to write and read it, and its size.

Usage:
    python bench/snapshot_cost.py [--gaussians 30000 150000] [--degrees 1 3] [--repeats 3]

The state has the shapes of a real fit's (:meth:`panogs_core.gaussians.fit.Fitter.state`): every parameter group
and its two Adam moments, at ``N`` Gaussians and SH degree ``d``. Figures are the median of the repeats.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from panogs_core.gaussians.spherical_harmonics import num_coefficients
from panogs_core.snapshots import StageSnapshot


def fit_state(n: int, degree: int) -> dict[str, object]:
    params = {
        "sh_dc": torch.randn(n, 1, 3),
        "sh_rest": torch.randn(n, num_coefficients(degree) - 1, 3),
        "opacity": torch.randn(n),
        "log_scales": torch.randn(n, 3),
        "quats": torch.randn(n, 4),
        "offsets": torch.zeros(n, 3),
    }
    trained = [torch.nn.Parameter(v.clone()) for name, v in params.items() if name != "offsets"]
    optimizer = torch.optim.Adam(trained)
    for p in trained:
        p.grad = torch.randn_like(p)
    optimizer.step()  # fills both moments
    return {
        "iteration": 100,
        "parameters": params,
        "optimizer": optimizer.state_dict(),
        "rng": json.dumps(np.random.default_rng(0).bit_generator.state),
        "order": list(range(60)),
        "scores_before": [12.0, 0.4],
        "seconds_per_iteration": [0.5] * 100,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[30_000, 150_000])
    parser.add_argument("--degrees", type=int, nargs="+", default=[1, 3])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print("| Gaussians | SH degree | size MB | write s | read s |")
    print("|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as folder:
        snapshot = StageSnapshot(Path(folder) / "appearance.partial.pt", key="bench")
        for n in args.gaussians:
            for degree in args.degrees:
                state = fit_state(n, degree)
                writes, reads = [], []
                for _ in range(args.repeats):
                    start = time.perf_counter()
                    snapshot.save(state)
                    writes.append(time.perf_counter() - start)
                    start = time.perf_counter()
                    assert snapshot.load() is not None
                    reads.append(time.perf_counter() - start)
                size = snapshot.path.stat().st_size / 2**20
                print(f"| {n} | {degree} | {size:.0f} | {statistics.median(writes):.3f} | "
                      f"{statistics.median(reads):.3f} |")  # fmt: skip


if __name__ == "__main__":
    main()
