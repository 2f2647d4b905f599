#!/usr/bin/env bash
# The GPU path in one command (at most 9 minutes: the steps' time limits add up to 540 s): installs the `gpu` extra (gsplat),
# runs the tests marked `gpu`, the photometric benchmark at the GPU schedule (held-out PSNR / SSIM, fit time, CUDA
# peak; docs/gaussians.md), the 2D maps stage per key frame on CUDA (SAM ViT-B at SAM's 32x32 grid and CLIP
# ViT-B/16, real sizes, random weights; docs/benchmarks.md "2D maps stage costs") and the stage times of a
# ScanNet-size `scan` room on CUDA, and writes the figures to
# $OUT/gpu_check.json (each step's exit status, wall time and numbers; a failed step does not stop the others).
#
# Usage: bench/gpu_check.sh [OUT]        (OUT defaults to bench/results/gpu_check)
#   SEVENSCENES=DIR   a 7-Scenes sequence (e.g. tsdf-fusion-python's data/) for the real-capture rows; without it
#                     the photometric benchmark runs on the synthetic room only
#   GPU_WHEELS=DIR    install the extra from this wheel folder (no index: for a machine without network)
#   SKIP_INSTALL=1    the extra is installed already
#   PY=...            the interpreter (default .venv/bin/python, else python3)
set -uo pipefail
cd "$(dirname "$0")/.."
out=$(realpath -m "${1:-bench/results/gpu_check}")
mkdir -p "$out"
py=${PY:-.venv/bin/python}
[ -x "$py" ] || py=python3
export HF_HUB_OFFLINE=1 PYTHONPATH=$PWD
steps="$out/steps.jsonl"
: > "$steps"

step() {  # step NAME LIMIT_S COMMAND...: run with a time limit, log to $out/NAME.log, record status and time
  local name=$1 limit=$2
  shift 2
  local t0 rc
  t0=$(date +%s%N)
  timeout "$limit" "$@" > "$out/$name.log" 2>&1
  rc=$?
  printf '{"step": "%s", "rc": %d, "wall_ms": %d}\n' "$name" "$rc" $((($(date +%s%N) - t0) / 1000000)) >> "$steps"
  echo "$name: exit $rc ($out/$name.log)"
}

"$py" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" \
  || echo "warning: torch sees no CUDA device; the GPU rows will say 'not run'"

if [ "${SKIP_INSTALL:-0}" != 1 ]; then
  if [ -n "${GPU_WHEELS:-}" ]; then
    step install 80 "$py" -m pip install --no-index --find-links "$GPU_WHEELS" -e ".[gpu]"
  else
    step install 80 "$py" -m pip install -e ".[gpu]"
  fi
fi
# gsplat compiles its kernels on first use: the parity tests pay for it once, the benchmark reuses the build.
step pytest_gpu 90 "$py" -m pytest -q -m gpu tests/core
photometric=(bench/gaussians.py photometric --schedules zero gpu --work "$out/work" --renders "$out/renders")
[ -n "${SEVENSCENES:-}" ] && photometric+=(--sevenscenes "$SEVENSCENES")
step photometric 150 "$py" "${photometric[@]}" --json "$out/photometric.json"
step maps2d 60 "$py" bench/maps2d.py --device cuda --frames 3 --warm 1 --cases sam-vit-b+clip-b16 \
  --root "$out/work/maps2d"
step scan_synth 90 "$py" -m panogs_core.cli synth "$out/work/scan-0" --preset scan --seed 0
step scan_run 70 "$py" -m panogs_core.cli run "$out/work/scan-0" --out "$out/work/scan-run" --no-resume -q

"$py" - "$out" <<'PY'
import json, sys
from pathlib import Path

out = Path(sys.argv[1])
result = {"steps": [json.loads(line) for line in (out / "steps.jsonl").read_text().splitlines() if line]}
try:
    import torch

    result["device"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    result["torch"] = torch.__version__
except ImportError:
    result["device"] = None
if (out / "photometric.json").is_file():
    result["photometric"] = json.loads((out / "photometric.json").read_text())
report = out / "work" / "scan-run" / "report.json"
if report.is_file():
    r = json.loads(report.read_text())
    result["scan_run"] = {
        "total_wall_s": r["total_wall_s"],
        "peak_rss_mb": r["peak_rss_mb"],
        "stages": {s["stage"]: s["wall_s"] for s in r["stages"]},
    }
maps_log = out / "maps2d.log"
if maps_log.is_file():  # the bench's markdown table: header and the case's row
    result["maps2d"] = [line for line in maps_log.read_text().splitlines() if line.startswith(("#", "| sam"))]
(out / "gpu_check.json").write_text(json.dumps(result, indent=1))
print(f"wrote {out / 'gpu_check.json'}")
PY
