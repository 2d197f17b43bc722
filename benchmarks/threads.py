"""How many threads a training takes by default, and what it costs, for code trees side by side.

Three conditions, each a fresh `cdrb train` of the quick preset for ``--steps`` steps with OMP_NUM_THREADS unset:

* ``idle``: nothing else runs, and nothing ran for a while (the 1-minute load average below 0.3);
* ``after a busy minute``: a CPU-bound process ran for ``--busy`` seconds and ended just before the training (the
  1-minute load average still counts it; the machine is idle);
* ``beside a busy process``: one CPU-bound process runs throughout.

For each: wall seconds, and the CPU the training used (user + system seconds / wall: ~1 for one thread, ~2 for two
on a 2-core machine). Trees are given as NAME=DIR (e.g. a worktree of an older commit).

Usage: python benchmarks/threads.py DEMOS.h5 BUFFER.h5 --tree before=/tmp/before --tree after=. [--steps 300]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BUSY = "import time\nt = time.time()\nwhile time.time() - t < {seconds}: pass\n"


def wait_idle(limit: float = 240.0) -> None:
    """Wait until the 1-minute load average has fallen below 0.3 (at most ``limit`` seconds): a machine idle for a
    while, on which every rule should take every core."""
    t = time.time()
    while os.getloadavg()[0] >= 0.3 and time.time() - t < limit:
        time.sleep(5)


def busy(seconds: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", BUSY.format(seconds=seconds)])


def train(tree: str, demos: str, buffer: str, steps: int, out: str) -> tuple[float, float]:
    """(wall seconds, CPU cores used on average) of one training in the code of ``tree``."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["PYTHONPATH"] = str(Path(tree).resolve())
    cmd = [sys.executable, "-m", "cdrb_cli", "train", demos, "--buffer", buffer, "--method", "cdrb", "--steps",
           str(steps), "--out", out, "--force"]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, capture_output=True, cwd=tree)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu / wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("demos")
    ap.add_argument("buffer")
    ap.add_argument("--tree", action="append", required=True, help="NAME=DIR of a checkout")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--busy", type=float, default=60.0, help="seconds of the busy minute before the training")
    args = ap.parse_args()
    demos, buffer = str(Path(args.demos).resolve()), str(Path(args.buffer).resolve())
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "m.h5")
        for name, tree in (t.split("=", 1) for t in args.tree):
            wait_idle()
            wall, cores = train(tree, demos, buffer, args.steps, out)
            rows.append((name, "idle", wall, cores))
            busy(args.busy).wait()
            wall, cores = train(tree, demos, buffer, args.steps, out)
            rows.append((name, "after a busy minute", wall, cores))
            hog = busy(3600)
            try:
                time.sleep(2)
                wall, cores = train(tree, demos, buffer, args.steps, out)
            finally:
                hog.kill()
                hog.wait()
            rows.append((name, "beside a busy process", wall, cores))
            print(f"{name}: done", file=sys.stderr)
    alone = {name: wall for name, cond, wall, _ in rows if cond == "idle"}
    print(f"| code | condition | `cdrb train` {args.steps} steps (s) | x its idle time | CPU cores used |")
    print("|---|---|---:|---:|---:|")
    for name, cond, wall, cores in rows:
        print(f"| {name} | {cond} | {wall:.1f} | {wall / alone[name]:.2f} | {cores:.2f} |")


if __name__ == "__main__":
    main()
