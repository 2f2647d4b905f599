"""One step's planes update, dense against sparse: is a lazy Adam over the rows a batch touches cheaper?

Usage:
    python bench/field_sparse_update.py RUN [--reps 100]

``RUN`` is a ``panogs run`` output directory (its ``stages/primitives.npz`` and ``stages/fusion.npz``): a real
batch of 1024 seen primitives gives the 24 corners per point. Prints this thread's CPU ms per update of the
field's way (zero the ``(cells, C)`` gradient, ``index_add_`` the batch, torch's fused Adam over every value)
and of a lazy Adam (the touched rows found by marking or by ``torch.unique``, their gradient summed, their two
moments and values gathered, updated and written back), and how many rows a batch touches.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from panogs_core.stages.language_field import field_bounds, plane_resolutions  # noqa: E402
from panogs_core.stages.language_field import triplane as tp  # noqa: E402
from panogs_core.stages.language_field.config import LanguageFieldConfig  # noqa: E402
from panogs_core.stages.language_field.corners import add_table_gradient, bilinear_corners  # noqa: E402


def cpu_ms(fn, reps: int) -> float:
    fn()
    t0 = time.thread_time()
    for _ in range(reps):
        fn()
    return 1e3 * (time.thread_time() - t0) / reps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--reps", type=int, default=100)
    args = parser.parse_args()
    torch.set_num_threads(1)
    points = np.load(args.run / "stages" / "primitives.npz")["points"]
    seen = np.load(args.run / "stages" / "fusion.npz")["weights"] > 0
    cfg = LanguageFieldConfig()
    bounds = field_bounds(points, cfg.bound_padding)
    resolutions = plane_resolutions(bounds, cfg)
    coords = tp._to_unit_cube(torch.from_numpy(points[seen]), torch.from_numpy(bounds))
    all_cells, all_weights = bilinear_corners(coords, resolutions)
    pick = torch.randperm(all_cells.shape[0], generator=torch.Generator().manual_seed(0))[: cfg.batch_size]
    cells, corner_weights = all_cells[pick], all_weights[pick]
    flat = cells.reshape(-1)
    count = sum(3 * r * r for r in resolutions)
    latent_grad = torch.randn(cells.shape[0], cfg.channels)
    table, exp_avg, exp_avg_sq = torch.randn(count, cfg.channels), torch.zeros(count, cfg.channels), None
    exp_avg_sq = torch.zeros(count, cfg.channels)
    grad, steps = torch.zeros_like(table), torch.zeros(())
    beta1, beta2 = cfg.betas

    def dense() -> None:
        add_table_gradient(grad, cells, corner_weights, latent_grad)
        steps.add_(1)
        torch._fused_adam_(
            [table], [grad], [exp_avg], [exp_avg_sq], [], [steps], lr=cfg.plane_lr, beta1=beta1, beta2=beta2,
            weight_decay=0.0, eps=1e-15, amsgrad=False, maximize=False,
        )  # fmt: skip

    mark, slot = torch.zeros(count, dtype=torch.bool), torch.zeros(count, dtype=torch.int64)

    def rows_by_marking() -> tuple[torch.Tensor, torch.Tensor]:
        mark.index_fill_(0, flat, True)
        rows = mark.nonzero().squeeze(1)
        mark.index_fill_(0, rows, False)
        slot.index_copy_(0, rows, torch.arange(rows.shape[0]))
        return rows, slot.index_select(0, flat)

    def rows_by_unique() -> tuple[torch.Tensor, torch.Tensor]:
        return torch.unique(flat, return_inverse=True)

    step = [0]

    def lazy(find) -> None:
        rows, inverse = find()
        values = (corner_weights.unsqueeze(2) * latent_grad.unsqueeze(1)).reshape(-1, cfg.channels)
        row_grad = torch.zeros(rows.shape[0], cfg.channels).index_add_(0, inverse, values)
        step[0] += 1
        correction1, correction2 = 1 - beta1 ** step[0], math.sqrt(1 - beta2 ** step[0])
        m = exp_avg.index_select(0, rows).lerp_(row_grad, 1 - beta1)
        v = exp_avg_sq.index_select(0, rows).mul_(beta2).addcmul_(row_grad, row_grad, value=1 - beta2)
        exp_avg.index_copy_(0, rows, m)
        exp_avg_sq.index_copy_(0, rows, v)
        table.index_add_(0, rows, m.div_(v.sqrt_().div_(correction2).add_(1e-15)), alpha=-cfg.plane_lr / correction1)

    touched = rows_by_marking()[0].shape[0]
    print(f"{touched} of {count} table rows touched by a batch of {cfg.batch_size}")
    print(f"dense (zero, index_add_, fused Adam): {cpu_ms(dense, args.reps):.2f} CPU ms")
    print(f"lazy, rows by marking:               {cpu_ms(lambda: lazy(rows_by_marking), args.reps):.2f} CPU ms")
    print(f"lazy, rows by torch.unique:          {cpu_ms(lambda: lazy(rows_by_unique), args.reps):.2f} CPU ms")


if __name__ == "__main__":
    main()
