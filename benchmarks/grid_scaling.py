"""Wall time of one grid of 8 small runs with 1 vs 2 local workers.

The grid: Maze Tight, MLP and CDRB x 4 training seeds (8 trainings of 400 steps with small nets, 8 evaluations
of 20 episodes, one report), on the shared demonstrations and buffer, which are built once before timing. Each
configuration starts from the same prepared folder with no trained model, so every one does the same work.

    python benchmarks/grid_scaling.py --json docs/results/grid_scaling.json [--backends pool,ray]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

GRID = """
out = "runs"
envs = ["maze-tight"]
methods = ["mlp", "cdrb"]
seeds = [0, 1, 2, 3]
demos = 300
k = 200
steps = 400
eval_episodes = 20

[[settings]]
train = ["--set", "horizon=32", "--set", "stride=5", "--set", "batch_size=16"]

[[settings]]
method = "cdrb"
train = ["--set", "net.dim=16", "--set", "method.diffusion_steps=16"]

[[settings]]
method = "mlp"
train = ["--set", "net.hidden=256,256"]
"""


def cdrb(*args, env=None) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cdrb_cli", *map(str, args)], check=True, env=env, capture_output=True)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--backends", default="pool,ray")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="cdrb-grid-scaling-"))
    (root / "grid.toml").write_text(GRID)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    # collect + cluster once (the untimed part): a one-seed grid of the same data
    prep = root / "prep"
    prep.mkdir()
    (prep / "grid.toml").write_text(GRID.replace("seeds = [0, 1, 2, 3]", "seeds = [0]").replace('"mlp", ', ""))
    cdrb("grid", prep / "grid.toml", "--backend", "pool", "-j", "1", env=env)
    rows = []
    for backend in args.backends.split(","):
        for workers in (1, 2):
            folder = root / f"{backend}-{workers}"
            (folder / "runs" / "maze-tight").mkdir(parents=True)
            for name in ("demos.h5", "buffer-k200.h5"):
                shutil.copy(prep / "runs" / "maze-tight" / name, folder / "runs" / "maze-tight" / name)
            (folder / "grid.toml").write_text(GRID)
            seconds = cdrb("grid", folder / "grid.toml", "--backend", backend, "-j", workers, env=env)
            summary = json.loads((folder / "runs" / "grid.json").read_text())
            rows.append({"backend": backend, "workers": workers, "wall_s": seconds, "counts": summary["counts"]})
            print(f"{backend:5s} {workers} worker(s): {seconds:6.1f} s  {summary['counts']}", flush=True)
    for backend in {r["backend"] for r in rows}:
        one, two = (next(r for r in rows if r["backend"] == backend and r["workers"] == w) for w in (1, 2))
        print(f"{backend}: 1 -> 2 workers, wall time ratio {one['wall_s'] / two['wall_s']:.2f}x")
    meta = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, torch threads 1 per task",
        "grid": "maze-tight, mlp+cdrb x 4 seeds: 8 trainings (400 steps) + 8 evals (20 episodes) + report",
        "rows": rows,
    }
    if args.json:
        args.json.write_text(json.dumps(meta, indent=1))
    shutil.rmtree(root)


if __name__ == "__main__":
    main()
