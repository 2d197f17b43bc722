#!/usr/bin/env bash
# One piece of a grid on a borrowed machine whose artifacts do not outlive it: run `cdrb grid` until a deadline,
# then pack what the pipeline cannot rebuild cheaply (every eval artifact, the grid's summary, the task log) into
# OUT_DIR, one archive per environment, so `cdrb select` / `cdrb report` can read them back on another machine.
# Models stay behind (they are re-trained from the same seed when a later piece needs them); evals are written
# without their plans (gpu_grid_evals.toml).
#
# Usage: bash benchmarks/gpu_grid.sh GRID_FILE OUT_DIR SECONDS [cdrb grid flags...]
#   e.g. bash benchmarks/gpu_grid.sh experiments/tune/fetch-curves.toml "$OUT" 480 \
#          --set device='"cuda"' --set 'envs=["fetch-reach-obstacle"]' -j 16
# The grid runs under `timeout SECONDS` (SIGTERM: running trainings keep their checkpoint and stop), so the packing
# still happens when the piece was too large; OUT_DIR/piece.json says how far it got.
set -uo pipefail
grid=${1:?usage: gpu_grid.sh GRID_FILE OUT_DIR SECONDS [grid flags...]}
out=${2:?usage: gpu_grid.sh GRID_FILE OUT_DIR SECONDS [grid flags...]}
seconds=${3:?usage: gpu_grid.sh GRID_FILE OUT_DIR SECONDS [grid flags...]}
shift 3
py=${PYTHON:-python3}
here=$(cd "$(dirname "$0")" && pwd)
work=${WORK:-runs/piece}
mkdir -p "$out" && out=$(cd "$out" && pwd)
{ nvidia-smi --query-gpu=name,memory.total --format=csv,noheader; nproc; } >"$out/machine.txt" 2>/dev/null || true

t0=$(date +%s)
timeout --signal=TERM --kill-after=30 "$seconds" \
  "$py" -m cdrb_cli grid "$grid" --backend pool --set "out=\"$work\"" --include "$here/gpu_grid_evals.toml" "$@" \
  >"$out/grid.stdout" 2>"$out/grid.log"
rc=$?
t1=$(date +%s)

# one archive per environment folder: its evals (every variant) and nothing else
for env_dir in "$work"/*/; do
  env=$(basename "$env_dir")
  (cd "$work" && find "$env" -path "*/eval-*.h5" ! -name "*.tmp-*" -print0 | sort -z |
    tar --null -T - -cJf "$out/evals-$env.tar.xz") || true
done
cp "$work/grid.json" "$out/grid.json" 2>/dev/null || true
tail -c 200000 "$out/grid.log" >"$out/grid.log.tail" && mv "$out/grid.log.tail" "$out/grid.log"

"$py" - "$rc" "$((t1 - t0))" "$work" "$out/piece.json" <<'EOF'
import json, sys
from pathlib import Path
rc, seconds, work, dest = int(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]), sys.argv[4]
summary = json.loads((work / "grid.json").read_text()) if (work / "grid.json").exists() else None
evals = sorted(str(p.relative_to(work)) for p in work.rglob("eval-*.h5") if ".tmp-" not in p.name)
models = sorted(str(p.relative_to(work)) for p in work.rglob("*.h5") if "/eval-" not in str(p) and ".tmp-" not in p.name)
info = {"grid_rc": rc, "timed_out": rc == 124, "seconds": seconds, "evals": len(evals), "models": models,
        "summary_tasks": None if summary is None else len(summary.get("tasks", []))}
json.dump(info, open(dest, "w"), indent=1)
print(json.dumps({k: v for k, v in info.items() if k != "models"}))
EOF
ls -la "$out"
