#!/usr/bin/env bash
# Training and sampling costs on a CUDA machine: the figures docs/benchmarks.md §1 quotes for one H200
# (their tables: docs/notebook/2026-11-26-sampler-throughput.md, docs/notebook/2026-11-26-gpu-training-cost.md).
#
# What it measures (each run alone, one after the other, so timings do not share the GPU):
#   * the ball sampler on CUDA against the dense reference (benchmarks/sampler_throughput.py --device cuda);
#   * ms per gradient step of every method at the paper preset on Fetch Push Obstacle and Maze Tight, and of CDRB
#     and Diffuser at the official Fetch size (T = 16, batch 64 = 32 x 2 accumulation), from two snapshots of one
#     run (the wall clock at step 100 and at the last step: CUDA start-up and the first steps are left out);
#   * the same for Diffusion-QL, from which its reference budget (1,000,000 steps) is extrapolated.
#
# Usage: bash benchmarks/gpu_timing.sh OUT_DIR [STEPS]
#   (METHODS, PRECISIONS, OFFICIAL=0, SAMPLER=0, DEMOS narrow it: see their lines below)
# Needs the cdrb dependencies importable (pip install -e . on the GPU machine, or PYTHONPATH with them), a CUDA
# torch, and about 5 minutes on an H100/H200. Writes OUT_DIR/gpu_timing.json and OUT_DIR/sampler_cuda.json.
set -euo pipefail
out=${1:?usage: gpu_timing.sh OUT_DIR [STEPS]}
steps=${2:-600}
mkdir -p "$out"
work=$(mktemp -d)
py=${PYTHON:-python3}
device=${DEVICE:-cuda}  # DEVICE=cpu: a dry run of this script on a machine without one
demos=${DEMOS:-1000}    # fewer (and SAMPLER=0) for a dry run
sampler=${SAMPLER:-1}
methods=${METHODS:-cdrb diffuser mlp diffusion-bc diffusion-ql}  # timed at the paper preset on Fetch Push Obstacle
precisions=${PRECISIONS:-float32}  # e.g. "float32 bfloat16": each method at each
official=${OFFICIAL:-1}  # 0: leave out the Maze Tight and official-Fetch-size rows
cdrb() { "$py" -m cdrb_cli "$@"; }

{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$out/gpu.txt"; } || true
"$py" -c 'import torch; print("torch", torch.__version__, "cuda", torch.cuda.is_available())' | tee -a "$out/gpu.txt"

for env in maze-tight fetch-push-obstacle; do  # 1,000 Maze Tight demos: the sampler benchmark's K = 100,000
  cdrb collect "$env" -n "$demos" --seed 0 --workers "${WORKERS:-8}" --out "$work/$env-demos.h5" >/dev/null
  cdrb cluster "$work/$env-demos.h5" --seed 0 --out "$work/$env-buffer.h5" >/dev/null
done

if [ "$sampler" = 1 ]; then  # its CPU reference rows are the slow part: cut at 90 s
  timeout 90 "$py" benchmarks/sampler_throughput.py --demos "$work/maze-tight-demos.h5" --device "$device" \
    --repeats 3 --json "$out/sampler_cuda.json" >"$out/sampler_cuda.txt" || echo "sampler benchmark stopped" >&2
fi

# one row per run: env, method, setting, parameters, ms per step between step 100 and the last
rows="$out/rows.jsonl"  # under OUT_DIR, so a run cut short keeps the rows it timed
: >"$rows"
time_run() {  # env method label extra-args...
  local env=$1 method=$2 label=$3
  shift 3
  local m="$work/$env-$method-$label.h5" buffer=()
  [ "$method" = cdrb ] && buffer=(--buffer "$work/$env-buffer.h5")
  cdrb train "$work/$env-demos.h5" "${buffer[@]}" --method "$method" --preset paper \
    --steps "$steps" --snapshot-at 100 --device "$device" --seed 0 --out "$m" "$@" >/dev/null
  "$py" - "$env" "$method" "$label" "$m" "$steps" >>"$rows" <<'EOF'
import json, sys
from pathlib import Path
from cdrb_cli import artifacts
env, method, label, path, steps = sys.argv[1:]
last = artifacts.load(Path(path), "model").manifest.state
first = artifacts.load(Path(path.replace(".h5", ".step100.h5")), "model").manifest.state
ms = 1000 * (last.wall_time_s - first.wall_time_s) / (int(steps) - 100)
print(json.dumps({"env": env, "method": method, "setting": label, "parameters": last.parameters,
                  "steps_timed": int(steps) - 100, "ms_per_step": round(ms, 3)}))
EOF
  tail -n 1 "$rows" >&2
}

for precision in $precisions; do  # bfloat16: the forward passes under autocast (TrainConfig.precision)
  label=paper && [ "$precision" = float32 ] || label=paper-$precision
  for method in $methods; do
    time_run fetch-push-obstacle "$method" "$label" --set precision="$precision"
  done
done
if [ "$official" = 1 ]; then
  for method in cdrb diffuser; do
    time_run maze-tight "$method" paper
    time_run fetch-push-obstacle "$method" official-fetch --set method.diffusion_steps=16
  done
fi

"$py" - "$rows" "$out/gpu_timing.json" <<'EOF'
import json, sys, platform
import torch
rows = [json.loads(line) for line in open(sys.argv[1])]
for r in rows:  # the reference budgets: paper preset 20k steps, official Fetch 5k, Diffusion-QL's 1M
    budget = 1_000_000 if r["method"] == "diffusion-ql" else (5000 if r["setting"] == "official-fetch" else 20000)
    r["budget_steps"] = budget
    r["budget_minutes"] = round(r["ms_per_step"] * budget / 60000, 1)
info = {"device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu", "torch": torch.__version__, "python": platform.python_version(),
        "rows": rows}
json.dump(info, open(sys.argv[2], "w"), indent=1)
print(json.dumps(info, indent=1))
EOF
