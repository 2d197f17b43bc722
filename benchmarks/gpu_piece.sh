#!/usr/bin/env bash
# The device side of a GPU piece: unpack the carry that benchmarks/gpu_carry.sh built, move the checkout to the
# absolute path it was built at (the grid's memos name their files by absolute path), check that cdrb imports,
# then run benchmarks/gpu_grid.sh. Run it from the repository root on the device with the carry named:
#   carry [".site.tar.xz", ".piece.tar.xz"], command
#   bash benchmarks/gpu_piece.sh /work/main 480 experiments/tune/fetch-curves.toml --set device='"cuda"' \
#        --set 'envs=["fetch-push-obstacle"]' -j 16
# The first argument is the checkout's path where the carry was built, the second the grid's deadline in seconds.
set -u
root=${1:?usage: gpu_piece.sh ROOT SECONDS GRID_FILE [grid flags...]}
seconds=${2:?usage: gpu_piece.sh ROOT SECONDS GRID_FILE [grid flags...]}
grid=${3:?usage: gpu_piece.sh ROOT SECONDS GRID_FILE [grid flags...]}
shift 3
t0=$(date +%s)
rm -rf /tmp/site && mkdir -p /tmp/site && tar -xJf .site.tar.xz -C /tmp/site || exit 3
if [ "$(pwd -P)" != "$root" ]; then mkdir -p "$(dirname "$root")" && rm -rf "$root" && cp -a . "$root" || exit 4; fi
cd "$root" || exit 4
if [ -f .piece.tar.xz ]; then mkdir -p runs && rm -rf runs/piece && tar -xJf .piece.tar.xz -C runs || exit 6; fi
unset MUJOCO_GL  # EGL would be tried first and its library is absent; cdrb renders nothing here
export PYTHONPATH=/tmp/site:$root PYTHONUNBUFFERED=1
python3 -c "import torch, mujoco, gymnasium_robotics, diffusers, cdrb_cli.cli; print(torch.cuda.get_device_name(0))" || exit 5
echo "prepared in $(($(date +%s) - t0)) s"
PYTHON=python3 bash benchmarks/gpu_grid.sh "$grid" "$OUT" "$seconds" "$@"
