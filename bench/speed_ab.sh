#!/usr/bin/env bash
# Side-by-side speed of two commits on one bundle, alternating, in one sitting (shared machines are noisy:
# compare within a run). Prints each run's total (and without the appearance stage, which runs after the results),
# peak RSS and the stage it was reached in, the wall and CPU seconds of the whole command (interpreter start and
# imports included), per-stage seconds and standard metrics.
#
# Usage: bench/speed_ab.sh OLD_REV [BUNDLE] [ROUNDS] [RUN_ARGS ...]
#   BUNDLE defaults to bench/results/speed/large-0 (make it with `panogs synth ... --preset large` or
#   `python bench/speed.py` once). The old commit is checked out in a temporary git worktree. RUN_ARGS go to
#   both sides' `panogs run`, e.g. the ScanNet-size case without the appearance fit:
#   bench/speed_ab.sh OLD_REV bench/results/speed/scannet-size-0 2 --set appearance.enabled=false
set -euo pipefail
cd "$(dirname "$0")/.."
old_rev=${1:?usage: bench/speed_ab.sh OLD_REV [BUNDLE] [ROUNDS]}
bundle=$(realpath "${2:-bench/results/speed/large-0}")
rounds=${3:-2}
run_args=("${@:4}")
py="$PWD/.venv/bin/python"  # not realpath: the venv link must stay a venv
work=$(mktemp -d)
git worktree add -q "$work/old" "$old_rev"
trap 'git worktree remove --force "$work/old"; rm -rf "$work"' EXIT
export HF_HUB_OFFLINE=1
for round in $(seq "$rounds"); do
  for side in old new; do
    if [ "$side" = old ]; then src="$work/old"; else src="$PWD"; fi
    # CPU seconds (user + system, every thread) next to the wall times: on a shared host they move far less.
    (cd "$src" && /usr/bin/time -f "%e %U %S" -o "$work/$side.cpu" \
      "$py" -c "import sys; sys.path.insert(0, '.'); from panogs_core.cli import main; main()" \
      run "$bundle" --out "$work/run-$side" --no-resume "${run_args[@]}" > "$work/$side.log" 2>&1)
    "$py" - "$work/run-$side" "$side" "$round" "$work/$side.cpu" <<'PY'
import json, sys
run, side, rnd, cpu_file = sys.argv[1:]
wall, user, system = map(float, open(cpu_file).read().split()[-3:])
r = json.load(open(f"{run}/report.json"))
m = json.load(open(f"{run}/metrics.json"))["standard"] if __import__("os").path.exists(f"{run}/metrics.json") else {}
stages = " ".join(f"{s['stage']}={s['wall_s']:.2f}" for s in r["stages"])
top = max(r["stages"], key=lambda s: s["peak_rss_mb"])
fit = sum(s["wall_s"] for s in r["stages"] if s["stage"] == "appearance")
# A report that has it says when the results were out; an older one's total less the fit is the same but for any
# wait for the bundle's hash, which its results' report made.
results = r.get("results_wall_s", r["total_wall_s"] - fit)
print(f"{side} round {rnd}: total {r['total_wall_s']:.1f} s (to the results {results:.1f} s), "
      f"peak {r['peak_rss_mb']:.0f} MB (in {top['stage']}), whole command {wall:.1f} s wall, {user + system:.1f} s CPU; "
      f"{stages}")
if m:
    print(f"    mIoU {m['miou']:.3f}  PRQ(T) {m['prq_thing']:.3f}  PRQ(S) {m['prq_stuff']:.3f}")
PY
  done
done
