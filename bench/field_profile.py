"""Where one language-field step goes, part by part, and what a whole fit costs and decodes.

Usage:
    python bench/field_profile.py RUN [--bundle BUNDLE] [--steps 150] [--fit] [--dtypes] [--set KEY=VALUE ...]
    ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 python bench/field_profile.py RUN   # AVX2 kernels only

``RUN`` is a ``panogs run`` output directory of ``BUNDLE`` (its ``stages/primitives.npz`` and
``stages/fusion.npz`` are the inputs of the field, exactly as the pipeline passes them). The step is the one
``triplane.train_model`` takes, timed part by part with one torch thread (the stage's setting): the batch's rows
and corners, the plane sampling, the targets' rows, the decoder and loss forward and backward (one function, by
hand), the planes' gradient scatter, Adam over the planes and over the decoder. ``--fit`` also times a whole
``fit_language_field`` (wall and CPU seconds) and, with ``--bundle``, scores its decoded features: the share of
annotated primitives whose nearest class text is the true class (seen / unseen by a key frame) and the mean
cosine to the fused rows. ``--dtypes`` times the step's largest product in float32 and bfloat16. ``--set``
overrides ``LanguageFieldConfig`` (JSON values: ``basis_dims=null``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.stages.fusion import FusedFeatures  # noqa: E402
from panogs_core.stages.language_field import field_bounds, fit_language_field, plane_resolutions  # noqa: E402
from panogs_core.stages.language_field import triplane as tp  # noqa: E402
from panogs_core.stages.language_field.config import LanguageFieldConfig  # noqa: E402
from panogs_core.stages.language_field.corners import BatchCorners, plane_table  # noqa: E402


class Timer:
    """CPU seconds per named part, summed over calls (torch runs one thread here, the caller's)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def __call__(self, name: str, fn, *args):
        t0 = time.thread_time()  # this thread's CPU time: other processes on a shared host barely move it
        out = fn(*args)
        self.seconds[name] = self.seconds.get(name, 0.0) + time.thread_time() - t0
        return out


def profile_steps(points: np.ndarray, fused: FusedFeatures, cfg: LanguageFieldConfig, steps: int) -> None:
    bounds = field_bounds(points, cfg.bound_padding)
    resolutions = plane_resolutions(bounds, cfg)
    model = tp.init_model(resolutions, fused.features.shape[1], cfg)
    t0 = time.perf_counter()
    data = tp.TrainingSet(
        points, fused.features, fused.weights, bounds, resolutions, torch.device("cpu"),
        basis_dims=cfg.basis_dims, seed=cfg.seed,
    )  # fmt: skip
    setup = time.perf_counter() - t0
    table = plane_table([p.detach() for p in model.planes])
    mlp = [w.detach() for w in model.mlp]
    if data.basis is not None:
        mlp[-1] = data.basis.t() @ mlp[-1]
    planes_adam = tp._Adam([table], lr=cfg.plane_lr, betas=cfg.betas, eps=1e-15, weight_decay=0.0)
    mlp_adam = tp._Adam(mlp, lr=cfg.lr, betas=cfg.betas, eps=1e-8, weight_decay=cfg.weight_decay)
    corners = BatchCorners(table)
    gen = torch.Generator().manual_seed(1)
    timer = Timer()
    done = 0
    with torch.no_grad():
        while done < steps:
            order = torch.randperm(len(data), generator=gen)
            for start in range(0, len(data), cfg.batch_size):
                if done == steps:
                    break
                idx = order[start : start + cfg.batch_size]
                cells = timer("batch rows and corners", data.cells.index_select, 0, idx)
                cw = timer("batch rows and corners", data.corner_weights.index_select, 0, idx)
                latent = timer("plane sampling", corners.latent, cells, cw)
                targets = timer("target rows", data.targets, idx)
                inv, sw = data.inverse_norms[idx], data.weights[idx]
                _, latent_grad, mlp_grads = timer(
                    "decoder + loss, fwd and bwd", tp._cosine_loss_and_gradients, mlp, latent, targets, inv, sw
                )
                grad = timer("plane gradient scatter", corners.table_gradient, latent_grad)
                timer("Adam, planes", planes_adam.step, [grad])
                timer("Adam, decoder", mlp_adam.step, mlp_grads)
                done += 1
    total = sum(timer.seconds.values())
    k = "D" if data.basis is None else data.basis.shape[1]
    print(f"{len(data)} training primitives, table {tuple(table.shape)}, targets {k}-d, kept energy "
          f"{data.kept_energy:.4f}; set-up (corners, basis, projection) {setup:.2f} s\n")  # fmt: skip
    print("| part | CPU ms / step | share |\n|---|---:|---:|")
    for name, sec in timer.seconds.items():
        print(f"| {name} | {1e3 * sec / steps:.2f} | {100 * sec / total:.0f} % |")
    epochs = max(cfg.epochs, math.ceil(cfg.min_steps / math.ceil(len(data) / cfg.batch_size)))
    per_fit = epochs * math.ceil(len(data) / cfg.batch_size)
    print(f"| **step** | **{1e3 * total / steps:.2f}** | x {per_fit} steps = {total / steps * per_fit:.1f} s |")


def fit_and_score(points: np.ndarray, fused: FusedFeatures, cfg: LanguageFieldConfig, bundle: Path | None) -> None:
    wall0, cpu0 = time.perf_counter(), time.process_time()
    field = fit_language_field(points, fused, cfg)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    seen = fused.weights > 0
    unit = fused.features[seen] / np.linalg.norm(fused.features[seen], axis=1, keepdims=True)
    cosine = float((field.features[seen] * unit).sum(axis=1).mean())
    line = f"\nfit: {wall:.2f} s wall, {cpu:.2f} s CPU; mean cosine to the fused rows (seen) {cosine:.4f}"
    if bundle is not None:
        from panogs_core.io.bundle import open_bundle

        scene = open_bundle(bundle)
        truth, vocabulary = scene.read_ground_truth(), scene.vocabulary
        assert truth is not None
        assert vocabulary is not None
        assert vocabulary.embeddings is not None
        text = vocabulary.embeddings / np.linalg.norm(vocabulary.embeddings, axis=1, keepdims=True)
        right = np.argmax(field.features @ text.T, axis=1) == truth.semantic
        annotated = truth.semantic >= 0
        line += f"; true class decoded: seen {right[annotated & seen].mean():.4f}"
        line += f", unseen {right[annotated & ~seen].mean():.4f}"
    print(line)


def product_dtypes(batch: int, dim: int, hidden: int, reps: int = 20) -> None:
    """CPU ms of the step's largest product, ``(B, D) @ (D, H)``, in float32 and in bfloat16 (a CPU without bf16
    units, e.g. AVX2 only, converts in software)."""
    gen = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, torch.bfloat16):
        a = torch.randn(batch, dim, generator=gen).to(dtype)
        b = torch.randn(dim, hidden, generator=gen).to(dtype)
        a @ b
        t0 = time.thread_time()
        for _ in range(reps):
            a @ b
        print(f"({batch}, {dim}) @ ({dim}, {hidden}) in {dtype}: {1e3 * (time.thread_time() - t0) / reps:.2f} CPU ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a panogs run directory (its stages/primitives.npz, fusion.npz)")
    parser.add_argument("--bundle", type=Path, default=None, help="the run's bundle, to score a --fit")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--fit", action="store_true")
    parser.add_argument("--dtypes", action="store_true", help="also time the largest product in float32 and bf16")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    overrides = {k: json.loads(v) for k, v in (item.split("=", 1) for item in args.sets)}
    overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    cfg = dataclasses.replace(LanguageFieldConfig(), **overrides)
    torch.set_num_threads(cfg.cpu_threads or torch.get_num_threads())
    points = np.load(args.run / "stages" / "primitives.npz")["points"]
    fused = FusedFeatures.load(args.run / "stages" / "fusion.npz")
    print(f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}, "
          f"MKL_ENABLE_INSTRUCTIONS={os.environ.get('MKL_ENABLE_INSTRUCTIONS', '-')}, {torch.get_num_threads()} "
          f"thread(s); load {os.getloadavg()[0]:.2f}")  # fmt: skip
    profile_steps(points, fused, cfg, args.steps)
    if args.dtypes:
        product_dtypes(cfg.batch_size, fused.features.shape[1], cfg.hidden_dims[-1])
    if args.fit:
        fit_and_score(points, fused, cfg, args.bundle)


if __name__ == "__main__":
    main()
