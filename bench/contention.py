"""Contention benchmark: one pipeline run per policy, on a quiet host and with a competing CPU load on every core,
stage times side by side.

Usage:
    python bench/contention.py [--preset small] [--load N] [--threads N] [--repeats 1]
                               [--appearance-iterations 20] [--policies worker,old] [--work bench/results/contention]

Policies, each run in a fresh process (the pools read their environment when numpy and torch load):
  worker  what ``panogs worker`` does (worker/cli.py ``limit_threads`` before the imports, ``set_torch_threads``
          in the job process): PANOGS_WORKER_THREADS threads (default: its share of the cores) and a passive wait.
  old     no limits: every pool sized from the machine's cores, OpenMP's and OpenBLAS's default spinning.

The load is ``--load`` busy-loop processes (default: one per core this process may use), started before the run
and stopped after it. The goal: under the load, no stage slows by much more than the share of the cores it lost
(with N load processes on N cores a run gets about half of them: 2-3x, not 25x). Stages under 0.5 s are listed
but their ratios are noise. Total time: about (2 x policies x repeats) pipeline runs of the preset with a short
appearance fit (small: a minute or two each on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# Imports nothing heavy: the child must set the limits before numpy and torch load.
from panogs_core.threads import THREAD_COUNT_VARIABLES, WAIT_POLICY, available_cores  # noqa: E402

POLICIES = ("worker", "old")
BUSY_LOOP = "while True:\n    pass\n"
NOISE_S = 0.5  # stages shorter than this: ratios not meaningful


def child(policy: str, bundle: Path, out: Path, overrides: dict[str, object], threads: int | None) -> None:
    """Run the pipeline once under ``policy`` in this (fresh) process; print the stage times as one JSON line."""
    used = None
    if policy == "worker":
        from service.settings import Settings
        from worker.cli import limit_threads

        values = {} if threads is None else {"worker_threads": threads}
        settings = Settings(_env_file=None, **values)  # type: ignore[call-arg, arg-type]
        used = limit_threads(settings)  # exactly what `panogs worker` does before its imports
        from panogs_core.threads import set_torch_threads

        set_torch_threads(used)  # what the job process does when its first task runs (worker/tasks.py)
    import torch

    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import run_pipeline

    result = run_pipeline(bundle, out, PipelineConfig().with_overrides(overrides), resume=False)
    stages = {t.name: round(t.wall_s, 3) for t in result.timings}
    usage = resource.getrusage(resource.RUSAGE_SELF)  # every thread of this process: spinning shows up here
    cpu_s = round(usage.ru_utime + usage.ru_stime, 2)
    record = {"policy": policy, "threads": used, "torch_threads": torch.get_num_threads(), "stages": stages}
    print(json.dumps({**record, "cpu_s": cpu_s}))


def start_load(count: int) -> list[subprocess.Popen[bytes]]:
    """``count`` processes that each keep one core busy until stopped."""
    return [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(count)]


def stop_load(procs: list[subprocess.Popen[bytes]]) -> None:
    for proc in procs:
        proc.terminate()
    for proc in procs:
        proc.wait(timeout=30)


def run_once(policy: str, bundle: Path, out: Path, args: argparse.Namespace, load: int) -> dict[str, object]:
    """One child run of ``policy``, with ``load`` busy processes beside it (0: quiet)."""
    # The child's environment holds no thread or wait variable of ours: each policy decides them itself.
    env = {k: v for k, v in os.environ.items() if k not in (*THREAD_COUNT_VARIABLES, *WAIT_POLICY)}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("HF_HUB_OFFLINE", "1")
    overrides = {"appearance": {"iterations": args.appearance_iterations}}
    argv = [sys.executable, __file__, "--child", policy, "--bundle", str(bundle), "--out", str(out),
            "--overrides", json.dumps(overrides)]  # fmt: skip
    if args.threads is not None:
        argv += ["--threads", str(args.threads)]
    busy = start_load(load)
    try:
        t0 = time.perf_counter()
        done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=args.run_timeout_s)
        wall = time.perf_counter() - t0
    finally:
        stop_load(busy)
    if done.returncode != 0:
        raise SystemExit(f"{policy} run failed ({done.returncode}):\n{done.stderr[-3000:]}")
    record = dict(json.loads(done.stdout.strip().splitlines()[-1]))
    record["wall_s"] = round(wall, 2)
    return record


def median_stages(records: list[dict[str, object]]) -> dict[str, float]:
    names = list(records[0]["stages"])  # type: ignore[call-overload]
    return {n: statistics.median(r["stages"][n] for r in records) for n in names}  # type: ignore[index]


def print_table(results: dict[tuple[str, str], list[dict[str, object]]], policies: list[str]) -> None:
    """Stage times (medians over repeats), quiet and loaded per policy, and the loaded/quiet ratio."""
    medians = {key: median_stages(recs) for key, recs in results.items()}
    names = list(next(iter(medians.values())))
    header = f"{'stage':<16}" + "".join(f"{p + ' quiet':>14}{p + ' loaded':>14}{'ratio':>8}" for p in policies)
    print(header)
    totals = dict.fromkeys(medians, 0.0)
    for name in names:
        row = f"{name:<16}"
        for p in policies:
            quiet, loaded = medians[(p, "quiet")][name], medians[(p, "loaded")][name]
            totals[(p, "quiet")] += quiet
            totals[(p, "loaded")] += loaded
            ratio = f"{loaded / quiet:.1f}x" if quiet >= NOISE_S else "-"
            row += f"{quiet:>13.2f}s{loaded:>13.2f}s{ratio:>8}"
        print(row)
    row = f"{'total':<16}"
    for p in policies:
        quiet, loaded = totals[(p, "quiet")], totals[(p, "loaded")]
        row += f"{quiet:>13.2f}s{loaded:>13.2f}s{loaded / quiet:>7.1f}x"
    print(row)
    row = f"{'CPU s (process)':<16}"  # threads spinning while they wait burn CPU time without progress
    for p in policies:
        quiet, loaded = (statistics.median(float(r["cpu_s"]) for r in results[(p, c)]) for c in ("quiet", "loaded"))  # type: ignore[arg-type]
        row += f"{quiet:>13.2f}s{loaded:>13.2f}s{loaded / quiet:>7.1f}x"
    print(row)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--load", type=int, default=None, help="busy processes (default: one per available core)")
    ap.add_argument("--threads", type=int, default=None, help="PANOGS_WORKER_THREADS of the worker policy")
    ap.add_argument("--repeats", type=int, default=1, help="runs per policy and condition (the median is shown)")
    ap.add_argument("--appearance-iterations", type=int, default=20, help="a short fit keeps the run short")
    ap.add_argument("--policies", default=",".join(POLICIES))
    ap.add_argument("--run-timeout-s", type=float, default=1800)
    ap.add_argument("--work", default="bench/results/contention")
    ap.add_argument("--child", choices=POLICIES, help=argparse.SUPPRESS)
    ap.add_argument("--bundle", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--overrides", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, Path(args.bundle), Path(args.out), json.loads(args.overrides), args.threads)
        return

    policies = [p for p in args.policies.split(",") if p]
    unknown = sorted(set(policies) - set(POLICIES))
    if unknown:
        raise SystemExit(f"--policies: unknown {unknown}; known: {list(POLICIES)}")
    cores = available_cores()
    load = args.load if args.load is not None else cores
    work = Path(args.work)
    bundle = work / f"{args.preset}-{args.seed}"
    if not (bundle / "scene.json").is_file():
        from panogs_core.synthetic import make_scene

        make_scene(bundle, preset=args.preset, seed=args.seed)
    print(f"{cores} core(s) available; load: {load} busy process(es); preset {args.preset}; "
          f"appearance.iterations={args.appearance_iterations}; {args.repeats} repeat(s)", flush=True)  # fmt: skip

    results: dict[tuple[str, str], list[dict[str, object]]] = {}
    for repeat in range(args.repeats):  # interleaved, so that a change in the host's own load hits every cell
        for policy in policies:
            for condition, busy in (("quiet", 0), ("loaded", load)):
                record = run_once(policy, bundle, work / f"run-{policy}-{condition}", args, busy)
                results.setdefault((policy, condition), []).append(record)
                print(f"  [{repeat + 1}] {policy:<6} {condition:<6} threads={record['threads']} "
                      f"torch={record['torch_threads']} wall {record['wall_s']:.1f} s, "
                      f"CPU {record['cpu_s']:.1f} s", flush=True)  # fmt: skip
    print()
    print_table(results, policies)
    (work / "contention.json").write_text(json.dumps({f"{p}/{c}": recs for (p, c), recs in results.items()}, indent=1))


if __name__ == "__main__":
    main()
