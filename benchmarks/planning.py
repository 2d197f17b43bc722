"""Plan quality and latency of several models on the same start/goal pairs, side by side in one run.

For each model: the fraction of planned states inside walls over N protocol pairs (seeded: identical pairs for
every model), the share of plans touching a wall, and the planning time per plan at batch 1 and batch 64.

Usage: python benchmarks/planning.py MODEL.h5 [MODEL.h5 ...] [--pairs 200] [--seed 0] [--markdown]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from cdrb_cli import artifacts
from cdrb_cli.envs.registry import family_of
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.seeding import STREAM_PLAN
from cdrb_cli.stages.plan import load_planner, sample_plans


def measure(model_path: Path, pairs: int, seed: int, timing_plans: int = 16, sampler=None, steps=None) -> dict:
    model = artifacts.load(model_path, "model")
    spec = model.manifest.env
    family = family_of(spec)
    method = load_planner(model)  # EMA weights
    starts, goals = family.reset_states(spec, family.draw_episodes(spec, pairs, seed, STREAM_PLAN))
    goals = family.goal_state(spec, goals)
    kw = dict(sampler=sampler, steps=steps)
    plans, *_ = sample_plans(method, starts, goals, 1, seed, batch_size=64, **kw)
    wall = family.in_collision(spec, plans[..., : spec.obs_dim])
    times = {}
    for batch in (1, 64):
        n = timing_plans if batch == 1 else 64 * 2
        s, g = starts[np.arange(n) % pairs], goals[np.arange(n) % pairs]
        sample_plans(method, s[:batch], g[:batch], 1, seed, batch_size=batch, **kw)  # warm-up
        t = time.perf_counter()
        sample_plans(method, s, g, 1, seed, batch_size=batch, **kw)
        times[batch] = (time.perf_counter() - t) / n
    cfg = model.manifest.config
    return {
        "model": str(model_path),
        "method": cfg.method.name,
        "preset": cfg.preset,
        "sampler": sampler or cfg.method.sampler,
        "steps": steps or getattr(cfg.method, "diffusion_steps", 1),
        "in_wall": float(wall.mean()),
        "plans_touching": float(wall.any(axis=1).mean()),
        "ms_per_plan_b1": 1000 * times[1],
        "ms_per_plan_b64": 1000 * times[64],
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fast-steps", type=int, default=0, help="also time diffusion models with this many steps")
    args = ap.parse_args()
    torch.set_num_threads(2)
    rows = []
    for m in args.models:
        rows.append(measure(m, args.pairs, args.seed))
        samplers = METHODS.get(rows[-1]["method"]).samplers
        if args.fast_steps and len(samplers) > 1:  # a diffusion method: time it with fewer denoising steps too
            fast = "ddim" if "ddim" in samplers else None  # Diffuser's fast sampler; CDRB keeps its own
            rows.append(measure(m, args.pairs, args.seed, sampler=fast, steps=args.fast_steps))
    print(
        f"| method | sampler (steps) | planned states in walls | plans touching a wall | ms/plan batch 1 | "
        f"ms/plan batch 64 |  ({args.pairs} pairs, seed {args.seed})"
    )
    print("|---|---|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['method']} ({r['preset']}) | {r['sampler']} ({r['steps']}) | {100 * r['in_wall']:.2f}% | "
            f"{100 * r['plans_touching']:.1f}% | {r['ms_per_plan_b1']:.1f} | {r['ms_per_plan_b64']:.2f} |"
        )


if __name__ == "__main__":
    main()
