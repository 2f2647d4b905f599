"""The language field's schedule: what fewer steps with another learning-rate schedule cost and decode.

Usage:
    python bench/field_schedule.py RUN --bundle BUNDLE [--rounds 1] --case NAME:KEY=VALUE;KEY=VALUE ...
    python bench/field_schedule.py bench/results/speed/run-scannet-size-0 \\
        --bundle bench/results/speed/scannet-size-0 --case default: \\
        --case 'e3:epochs=3;min_steps=200'

``RUN`` is a ``panogs run`` output directory of ``BUNDLE`` (its ``stages/primitives.npz`` and
``stages/fusion.npz``). Each case overrides ``LanguageFieldConfig`` (JSON values) and fits the whole field
(``fit_language_field``, one torch thread, the stage's setting) in this process; the cases alternate, round
after round. Per fit it prints the steps, the CPU seconds of the fit (this process's), the mean cosine of the
decoded to the fused rows (seen primitives), and the share of annotated primitives whose nearest class text is
the true class, seen and unseen by a key frame.
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

from panogs_core.io.bundle import open_bundle  # noqa: E402
from panogs_core.stages.fusion import FusedFeatures  # noqa: E402
from panogs_core.stages.language_field import fit_language_field  # noqa: E402
from panogs_core.stages.language_field.config import LanguageFieldConfig  # noqa: E402


def parse_case(text: str) -> tuple[str, LanguageFieldConfig]:
    name, _, settings = text.partition(":")
    overrides: dict[str, object] = {}
    for item in filter(None, settings.split(";")):
        key, _, value = item.partition("=")
        parsed = json.loads(value)
        overrides[key] = tuple(parsed) if isinstance(parsed, list) else parsed
    return name, dataclasses.replace(LanguageFieldConfig(), **overrides)  # type: ignore[arg-type]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--bundle", type=Path, required=True)
    parser.add_argument("--case", dest="cases", action="append", required=True, metavar="NAME:KEY=VALUE;...")
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    cases = [parse_case(text) for text in args.cases]
    points = np.load(args.run / "stages" / "primitives.npz")["points"]
    fused = FusedFeatures.load(args.run / "stages" / "fusion.npz")
    scene = open_bundle(args.bundle)
    truth, vocabulary = scene.read_ground_truth(), scene.vocabulary
    assert truth is not None
    assert vocabulary is not None
    assert vocabulary.embeddings is not None
    text = vocabulary.embeddings / np.linalg.norm(vocabulary.embeddings, axis=1, keepdims=True)
    seen = fused.weights > 0
    annotated = truth.semantic >= 0
    unit = fused.features[seen] / np.linalg.norm(fused.features[seen], axis=1, keepdims=True)
    print(f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}; "
          f"{int(seen.sum())} training primitives; load {os.getloadavg()[0]:.2f}\n")  # fmt: skip
    print("| case | round | steps | fit CPU s | mean cosine | true class seen | true class unseen |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for round_ in range(1, args.rounds + 1):
        for name, cfg in cases:
            per_epoch = math.ceil(int(seen.sum()) / cfg.batch_size)
            steps = max(cfg.epochs, math.ceil(cfg.min_steps / per_epoch)) * per_epoch
            cpu0 = time.process_time()
            field = fit_language_field(points, fused, cfg)
            cpu = time.process_time() - cpu0
            cosine = float((field.features[seen] * unit).sum(axis=1).mean())
            right = np.argmax(field.features @ text.T, axis=1) == truth.semantic
            print(f"| {name} | {round_} | {steps} | {cpu:.2f} | {cosine:.4f} | {right[annotated & seen].mean():.4f} | "
                  f"{right[annotated & ~seen].mean():.4f} |", flush=True)  # fmt: skip
    print(f"\nload {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
