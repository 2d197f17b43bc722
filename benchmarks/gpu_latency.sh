#!/usr/bin/env bash
# The device side of the GPU latency check, in one call: unpack the packages benchmarks/gpu_carry.sh built, run
# the CUDA tests, then time planning on the GPU with benchmarks/latency.py for this checkout (with and without its
# fast paths) and for an older tree, writing the tables and logs under $OUT. Prepare here:
#   bash benchmarks/gpu_carry.sh
#   mkdir -p .bench/before && git archive OLD_COMMIT cdrb_cli | tar -x -C .bench/before   # .bench/ in .git/info/exclude
#   cp MODEL.h5 .bench/
# then run on the device, carrying [".site.tar.xz", ".bench"]:
#   bash benchmarks/gpu_latency.sh .bench/MODEL.h5 [...]
# COMPILE=1 adds rows with runtime="compile" (torch.compile; each batch size compiles first, ~30 s on an H200).
set -u
rm -rf /tmp/site && mkdir -p /tmp/site && tar -xJf .site.tar.xz -C /tmp/site || exit 3
unset MUJOCO_GL  # no renderer is needed here
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
python3 -c "import torch, cdrb_cli.cli; print(torch.__version__, torch.cuda.get_device_name(0))" || exit 5
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
timeout "${TEST_SECONDS:-240}" python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py >"$OUT/test_cuda.log" 2>&1
echo "tests/test_cuda.py: exit $?"; tail -3 "$OUT/test_cuda.log"
for model in "$@"; do
  name=$(basename "$model" .h5)
  timeout "${BENCH_SECONDS:-200}" python3 benchmarks/latency.py "$model" --device cuda --tree after=. \
    --tree before=.bench/before --variants ${COMPILE:+--compile} --rounds "${ROUNDS:-2}" --markdown \
    >"$OUT/latency-$name.md" 2>"$OUT/latency-$name.log"
  echo "latency $name: exit $?"; cat "$OUT/latency-$name.md"; tail -2 "$OUT/latency-$name.log"
done
