#!/usr/bin/env bash
# Build what a borrowed GPU machine needs beside the working tree, as files to name in the device call's `carry`:
#   .site.tar.xz   the Python packages cdrb needs that the device image lacks (or has in another version), built
#                  for CPython 3.12 x86-64 from the versions installed here (.venv), trimmed of assets no
#                  cdrb environment loads (the Adroit and kitchen models, MuJoCo's headers and experimental code);
#   .piece.tar.xz  (with GRID and ENV) the grid's `out` folder after its collection and clustering ran here, so the
#                  device spends its minutes on training and evals: the grid's memos vouch for the artifacts, and
#                  they match there when the checkout sits at the same absolute path (the device script copies it).
# Both names are in .gitignore: they travel only when a call's `carry` names them. The device side is
# benchmarks/gpu_piece.sh.
#
# Usage: bash benchmarks/gpu_carry.sh [GRID ENV [grid flags...]]   (the flags as the device's grid will get them,
#   e.g. the methods it trains; the collection and clustering do not depend on them)
#   e.g. bash benchmarks/gpu_carry.sh experiments/tune/fetch-curves.toml fetch-push-obstacle \
#          --set 'methods=["diffuser","cdrb"]'
set -euo pipefail
cd "$(dirname "$0")/.."
py=${PYTHON:-.venv/bin/python}
packages=(mujoco gymnasium gymnasium-robotics pettingzoo farama-notifications glfw PyOpenGL pydantic pydantic-core
  annotated-types typing-inspection typing-extensions typer click shellingham annotated-doc diffusers
  importlib-metadata)
pins=()
for p in "${packages[@]}"; do pins+=("$p==$("$py" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$p")"); done
whl=$(mktemp -d) site=$(mktemp -d)
trap 'rm -rf "$whl" "$site"' EXIT
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 -d "$whl" "${pins[@]}"
"$py" -m pip install -q --no-deps --no-compile --target "$site" --only-binary=:all: --python-version 3.12 \
  --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 "$whl"/*.whl
rm -rf "$site"/mujoco/experimental "$site"/mujoco/include "$site"/gymnasium_robotics/envs/assets/{kitchen_franka,adroit_hand} \
  "$site"/gymnasium_robotics/envs/assets/stls/hand
tar -cJf .site.tar.xz -C "$site" .
ls -la .site.tar.xz

if [ $# -ge 2 ]; then
  grid=$1 env=$2
  shift 2
  # the same flags as gpu_piece.sh's grid, so the memos of the collection and clustering match there; the
  # trainings fail here at once (no CUDA) and are not memoised
  "$py" -m cdrb_cli grid "$grid" --backend pool --set 'out="runs/piece"' --set device='"cuda"' \
    --set "envs=[\"$env\"]" --retries 0 -j 2 "$@" >/dev/null 2>&1 || true
  ls runs/piece/.grid/collect_"$env".json >/dev/null
  # this env's collection and clustering with their memos, nothing else the folder holds
  (cd runs && find piece/.grid -name "collect_$env.json" -o -name "cluster_${env}_*.json" -o -name "cluster_$env.json";
    find "piece/$env" -maxdepth 1 \( -name demos.h5 -o -name "buffer-*.h5" \)) | sort |
    tar -cf - -C runs -T - | xz -T2 -3 >.piece.tar.xz
  ls -la .piece.tar.xz  # with the working tree it must stay under the device's 64 MiB
fi
