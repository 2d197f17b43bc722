"""Planning latency and plan safety, side by side for code trees (this checkout and, e.g., a worktree of an older
commit), measured in one run on one machine.

For each tree a fresh process loads the model and measures, on the same protocol pairs:

* ms per plan at batch 1 (median of ``--plans`` single plans, each its own sampler call, as a robot re-planning
  makes them), and per plan at batch 64 and 1,000 (the mean over whole batches);
* planned states inside obstacles and plans through one (a state in one, or a straight step between two states
  crossing one), over ``--pairs`` pairs, so a faster setting that plans less safely shows it.

The trees run alternately, ``--rounds`` times (the median of the rounds is kept), so a machine that slows down
for a while slows both. ``--variants`` runs one tree twice: as it is, and with its fast paths off where it has them
(the traced network, CUDA graphs), to show what each adds; ``--onnx`` once more with the network in ONNX Runtime
(``runtime="onnx"``), ``--auto`` with the Python API's default rule (``runtime="auto"``: ONNX Runtime for small
batches, torch for large ones; its safety columns are then torch's, measured at batch 64), ``--compile`` with the
network through ``torch.compile`` (``runtime="compile"``; its compile time is spent in the warm-up, outside the
timings).

Usage:
  git worktree add /tmp/before 9a30df8
  python benchmarks/latency.py MODEL.h5 --tree before=/tmp/before --tree after=. [--device cuda] [--markdown]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path


def measure(
    model_path: str,
    device: str,
    pairs: int,
    plans: int,
    batches: list[int],
    seed: int,
    fast: bool,
    steps=None,
    runtime: str | None = None,
) -> dict:
    """In a worker process: the figures of one tree (imported from PYTHONPATH)."""
    import numpy as np
    import torch

    from cdrb_cli import artifacts
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.seeding import STREAM_PLAN
    from cdrb_cli.stages.plan import load_planner, sample_plans

    model = artifacts.load(Path(model_path), "model")
    spec = model.manifest.env
    family = family_of(spec)
    method = load_planner(model, device=device)
    if not fast:  # the tree's fast paths off, where it has them
        type(method).trace_sampling = False
        if hasattr(method, "cuda_graphs"):
            type(method).cuda_graphs = False
    if runtime:  # the network in another runtime (ONNX Runtime, torch.compile), from the first call
        try:
            from cdrb_cli.nets.runtime import RUNTIMES
        except ImportError:
            RUNTIMES = ()
        if not hasattr(method, "use_runtime") or runtime not in RUNTIMES:
            return {"skipped": f"this tree has no runtime {runtime!r}"}
        method.use_runtime(runtime)
    starts, goals = family.reset_states(spec, family.draw_episodes(spec, pairs, seed, STREAM_PLAN))
    goals = family.goal_state(spec, goals)

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    kw = {"steps": steps, "device": device}
    out, _, _, _, _ = sample_plans(method, starts, goals, 1, seed, batch_size=64, **kw)
    states = out[..., : spec.obs_dim]
    result = {
        "in_obstacle_pct": 100 * float(np.asarray(family.in_collision(spec, states)).mean()),
        "through_obstacle_pct": 100 * float(np.asarray(family.path_in_collision(spec, states)).mean()),
    }
    for batch in batches:
        n = plans if batch == 1 else max(1, 2 * 64 // batch)  # single plans, or whole batches
        idx = np.arange(n * batch) % pairs
        s, g = starts[idx], goals[idx]
        sample_plans(method, s[:batch], g[:batch], 1, seed, batch_size=batch, **kw)  # warm-up
        times = []
        for i in range(n):
            sl = slice(i * batch, (i + 1) * batch)
            sync()
            t = time.perf_counter()
            sample_plans(method, s[sl], g[sl], 1, seed + i, batch_size=batch, **kw)
            sync()
            times.append((time.perf_counter() - t) / batch)
        result[f"ms_b{batch}"] = 1000 * (statistics.median(times) if batch == 1 else statistics.mean(times))
    result["threads"] = torch.get_num_threads()
    result["device"] = torch.cuda.get_device_name() if device.startswith("cuda") else "cpu"
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--tree", action="append", default=[], help="NAME=DIR of a checkout (default: this one)")
    ap.add_argument("--variants", action="store_true", help="also run each tree with its fast paths off")
    ap.add_argument("--onnx", action="store_true", help="also run each tree with runtime onnx (ONNX Runtime)")
    ap.add_argument("--compile", action="store_true", help="also run each tree with runtime compile (torch.compile)")
    ap.add_argument("--auto", action="store_true", help="also run each tree with runtime auto (the API's default)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--plans", type=int, default=30, help="single plans timed at batch 1")
    ap.add_argument("--batches", default="1,64,1000")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sample-steps", type=int, default=None, help="denoising steps (default: the model's all)")
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    if args.worker:
        import torch

        torch.set_num_threads(args.threads)
        fast, runtime = args.worker != "plain", args.worker if args.worker in ("onnx", "compile", "auto") else None
        fig = measure(
            args.model, args.device, args.pairs, args.plans, batches, args.seed, fast, args.sample_steps, runtime
        )
        print(json.dumps(fig))
        return
    here = Path(__file__).resolve().parent.parent
    trees = [t.split("=", 1) for t in args.tree] or [["this", str(here)]]
    runs = [(name, path, "fast") for name, path in trees]
    if args.variants:
        runs += [(f"{name}, fast paths off", path, "plain") for name, path in trees]
    if args.onnx and args.device != "cpu":
        print(f"--onnx: ONNX Runtime runs on the CPU, not {args.device}: no onnx rows", file=sys.stderr)
    elif args.onnx:
        runs += [(f"{name}, onnx runtime", path, "onnx") for name, path in trees]
    if args.compile:
        runs += [(f"{name}, compile runtime", path, "compile") for name, path in trees]
    if args.auto:
        runs += [(f"{name}, auto runtime", path, "auto") for name, path in trees]
    figures: dict[str, list[dict]] = {name: [] for name, _, _ in runs}
    for r in range(args.rounds):
        for name, path, mode in runs:
            model = str(Path(args.model).resolve())
            cmd = [sys.executable, str(Path(__file__).resolve()), model, "--worker", mode, "--device", args.device,
                   "--threads", str(args.threads), "--pairs", str(args.pairs), "--plans", str(args.plans),
                   "--batches", args.batches, "--seed", str(args.seed)]  # fmt: skip
            if args.sample_steps:
                cmd += ["--sample-steps", str(args.sample_steps)]
            paths = [str(Path(path).resolve()), *filter(None, [os.environ.get("PYTHONPATH")])]
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths), OMP_NUM_THREADS=str(args.threads))
            done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=path)
            if done.returncode:
                sys.exit(f"{name}: {done.stderr.strip().splitlines()[-1] if done.stderr.strip() else 'failed'}")
            fig = json.loads(done.stdout.strip().splitlines()[-1])
            print(f"round {r + 1}: {name}: {fig}", file=sys.stderr)
            if "skipped" not in fig:
                figures[name].append(fig)
    runs = [run for run in runs if figures[run[0]]]  # a row skipped (said above) in every round has no figures
    header = ["code", "device", "threads", *[f"ms/plan batch {b}" for b in batches], "states in obstacles (%)",
              "plans through an obstacle (%)"]  # fmt: skip
    rows = []
    for name, _, _ in runs:
        f = figures[name]
        med = {k: statistics.median(x[k] for x in f) for k in f[0] if isinstance(f[0][k], float)}
        rows.append([name, f[0]["device"], str(f[0]["threads"]), *[f"{med[f'ms_b{b}']:.2f}" for b in batches],
                     f"{med['in_obstacle_pct']:.2f}", f"{med['through_obstacle_pct']:.1f}"])  # fmt: skip
    if args.markdown:
        print("| " + " | ".join(header) + " |")
        print("|" + "---|" * 3 + "---:|" * (len(header) - 3))
        for row in rows:
            print("| " + " | ".join(row) + " |")
    else:
        print(json.dumps([dict(zip(header, row)) for row in rows], indent=2))


if __name__ == "__main__":
    main()
