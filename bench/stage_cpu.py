"""CPU seconds of the heavy stages (primitives, visibility, fusion, language field) at 1 and 2 threads, alternating.

Usage:
    python bench/stage_cpu.py RUN BUNDLE [--stages primitives visibility fusion language_field] [--threads 1 2]
        [--repeats 2] [--src DIR ...] [--profile STAGE]

``RUN`` is a ``panogs run`` output directory of ``BUNDLE``: each stage reads its inputs from the run's checkpoints
(``stages/primitives.npz``, ``visibility.npz``, ``fusion.npz``), as the pipeline hands them over. Every
(source, stage, threads) measurement is a fresh child process pinned to that many cores (``sched_setaffinity``:
open3d's TBB pool follows the affinity), with the thread variables of :mod:`panogs_core.threads` set before numpy
and torch load and torch's count set to the same number, the way ``panogs run --threads N`` starts. The rounds
alternate sources and thread counts in one sitting; the process's CPU seconds (user + system, every thread) move
far less than wall seconds on a shared host. ``--src`` names source trees to compare (default: this one), e.g. a
``git worktree`` of an older commit. ``--profile STAGE`` prints a cProfile of one run of that stage instead.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("primitives", "visibility", "fusion", "language_field")


def run_stage(stage: str, run: Path, bundle_path: Path, threads: int) -> None:
    """In the child: run one stage on the run's checkpoints and print its CPU and wall seconds as JSON."""
    import numpy as np

    from panogs_core.io.bundle import open_bundle
    from panogs_core.threads import set_torch_threads

    set_torch_threads(threads)
    bundle = open_bundle(bundle_path)
    stages = run / "stages"
    if stage == "primitives":
        from panogs_core.stages.primitives import PrimitivesConfig, build_primitives

        def work() -> object:
            return build_primitives(bundle, PrimitivesConfig())
    elif stage == "visibility":
        from panogs_core.stages.visibility import VisibilityConfig, compute_visibility

        points = np.load(stages / "primitives.npz")["points"]

        def work() -> object:
            return compute_visibility(bundle, points, VisibilityConfig())
    elif stage == "fusion":
        from panogs_core.stages.fusion import FusionConfig, fuse_features
        from panogs_core.stages.visibility import Visibility

        vis = Visibility.load(stages / "visibility.npz")
        count = int(np.load(stages / "primitives.npz")["points"].shape[0])

        def work() -> object:
            return fuse_features(bundle, vis, count, FusionConfig(fuse_colors=False))
    else:
        from panogs_core.stages.fusion import FusedFeatures
        from panogs_core.stages.language_field import LanguageFieldConfig, fit_language_field

        points = np.load(stages / "primitives.npz")["points"]
        fused = FusedFeatures.load(stages / "fusion.npz")

        def work() -> object:
            return fit_language_field(points, fused, LanguageFieldConfig(cpu_threads=threads))

    cpu0, wall0 = time.process_time(), time.perf_counter()
    work()
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    print(json.dumps({"cpu_s": round(cpu, 3), "wall_s": round(wall, 3), "load": round(os.getloadavg()[0], 2)}))


def child(src: Path, stage: str, run: Path, bundle: Path, threads: int, profile: bool = False) -> dict[str, float]:
    """One measurement in a fresh process pinned to ``threads`` cores, importing the code of ``src``."""
    sys.path.insert(0, str(src))
    from panogs_core.threads import thread_environment

    env = {**os.environ, **thread_environment(threads), "PYTHONPATH": str(src), "HF_HUB_OFFLINE": "1"}
    cores = sorted(os.sched_getaffinity(0))[:threads]
    code = (
        f"import os, sys; os.sched_setaffinity(0, {cores}); sys.path.insert(0, {str(src)!r}); "
        f"sys.path.insert(0, {str(REPO / 'bench')!r}); import stage_cpu; "
        f"stage_cpu.run_stage({stage!r}, __import__('pathlib').Path({str(run)!r}), "
        f"__import__('pathlib').Path({str(bundle)!r}), {threads})"
    )
    args = [sys.executable, "-c", code]
    if profile:
        args = [sys.executable, "-c", f"import cProfile, pstats; cProfile.run({code!r}, '/tmp/stage.prof'); "
                "pstats.Stats('/tmp/stage.prof').sort_stats('tottime').print_stats(25)"]  # fmt: skip
    out = subprocess.run(args, env=env, cwd=src, check=True, capture_output=True, text=True).stdout
    if profile:
        print(out)
        return {}
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("bundle", type=Path)
    parser.add_argument("--stages", nargs="+", choices=STAGES, default=list(STAGES))
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--src", nargs="+", type=Path, default=[REPO])
    parser.add_argument("--profile", choices=STAGES, default=None)
    args = parser.parse_args()
    run, bundle = args.run.resolve(), args.bundle.resolve()
    if args.profile:
        child(args.src[0].resolve(), args.profile, run, bundle, args.threads[0], profile=True)
        return
    print(f"CPU: {_cpu_model()}; {os.cpu_count()} cores; load {os.getloadavg()[0]:.2f} at the start\n")
    print("| round | source | stage | threads | CPU s | wall s | load |\n|---|---|---|---:|---:|---:|---:|")
    for rnd in range(1, args.repeats + 1):
        for stage in args.stages:
            for src in args.src:
                for threads in args.threads:
                    r, name = child(src.resolve(), stage, run, bundle, threads), src.resolve().name
                    print(f"| {rnd} | {name} | {stage} | {threads} | {r['cpu_s']:.2f} | {r['wall_s']:.2f} | "
                          f"{r['load']:.1f} |", flush=True)  # fmt: skip


def _cpu_model() -> str:
    """The model name and the widest AVX level ``/proc/cpuinfo`` lists."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return "unknown"
    model = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")), "?")
    flags = next((line.split(":", 1)[1].split() for line in info.splitlines() if line.startswith("flags")), [])
    level = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    return f"{model}, {level}"


if __name__ == "__main__":
    main()
