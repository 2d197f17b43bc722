"""How closely a closed-loop policy's actions follow the expert's on held-out demonstration states.

    python benchmarks/policy_actions.py runs/cmp/maze/sweep/diffusion-ql-quick.h5 runs/cmp/maze/diffusion-bc-tuned-s0.h5

For each model, two sets of held-out (state, goal) pairs from its demonstrations' validation split (episodes the model
never trained on), the goal always the episode's final state (where the expert was sent):
* ``transitions``: ``--pairs`` uniformly drawn steps. Mid-episode the state's velocity already says where the expert
  is heading, so a policy can score well here while ignoring the goal;
* ``first step``: every validation episode's first state. The robot is at rest; only the goal says which way to go.
The policy acts once on each; the script prints one JSON line per model, set and sampler: the mean absolute action
error, the median cosine between policy and expert action, the share of actions more than 25 degrees off (cosine <
0.9) and the ratio of mean action norms. Each model is measured with every sampler its config allows (the ones
benchmarks/comparison.py tunes), its own first: for Diffusion-QL the plain DDPM sample (``--sampler ddpm``: no
Q-based pick) separates the actor's imitation from the critic's choice.
docs/notebook/2026-11-25-maze-policies.md uses these to explain Diffusion-QL's maze rows.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def held_out(demos, normalizer, obs_dim: int, goal_dims, n: int, seed: int):
    """(states, goals, expert actions), raw, of ``n`` validation-split transitions with the final state as goal."""
    from cdrb_cli.data import TransitionSampler

    rows = TransitionSampler(demos, "state-action", normalizer, 1, "valid", 0.0).sample(n, np.random.default_rng(seed))
    raw = normalizer.unnormalize(rows.astype(np.float64))
    return raw[:, 0, :obs_dim], raw[:, -1, list(goal_dims)], raw[:, 0, obs_dim:]


def first_steps(demos, obs_dim: int, goal_dims):
    """(states, goals, expert actions), raw, at the first step of every validation episode, its final state as goal."""
    from cdrb_cli.buffer import demo_features

    raw = demo_features(demos, "state-action").astype(np.float64)
    ids = demos.episode_ids("valid")
    first = demos.episode_start[ids]
    last = first + demos.episode_length[ids] - 1
    return raw[first, :obs_dim], raw[last][:, list(goal_dims)], raw[first, obs_dim:]


def agreement(actions: np.ndarray, expert: np.ndarray) -> dict:
    """Mean |a - a*|, median cosine, the share with cosine < 0.9 (a zero action has cosine 0) and the ratio of mean
    action norms (below 1: the policy pushes more weakly than the expert)."""
    na, ne = np.linalg.norm(actions, axis=1), np.linalg.norm(expert, axis=1)
    ok = (na > 0) & (ne > 0)
    cos = np.where(ok, (actions * expert).sum(axis=1) / np.where(ok, na * ne, 1.0), 0.0)
    return {
        "mean_abs_error": round(float(np.abs(actions - expert).mean()), 4),
        "median_cosine": round(float(np.median(cos)), 4),
        "off_by_25deg": round(float((cos < 0.9).mean()), 4),
        "norm_ratio": round(float(na.mean() / ne.mean()), 4),
    }


def measure(path: Path, n: int, seed: int) -> list[dict]:
    from cdrb_cli import artifacts
    from cdrb_cli.methods.checkpoint import load_method
    from cdrb_cli.methods.registry import METHODS

    model = artifacts.load(path, "model")
    policy = load_method(model)
    entry = METHODS.get(policy.name)
    if entry.kind != "policy":
        raise SystemExit(f"{path}: {policy.name} is a planner; this script measures closed-loop policies")
    demos = artifacts.load(model.manifest.parents[0].path, "demos")
    sets = {
        "transitions": held_out(demos, policy.normalizer, policy.obs_dim, policy.goal_dims, n, seed),
        "first step": first_steps(demos, policy.obs_dim, policy.goal_dims),
    }
    samplers = [policy.config.method.sampler, *entry.samplers]
    out = []
    for name, (states, goals, expert) in sets.items():
        for sampler in dict.fromkeys(samplers):
            policy.config = policy.config.model_copy(
                update={"method": policy.config.method.model_copy(update={"sampler": sampler})}
            )
            policy.reset(len(states), np.random.default_rng(seed))
            actions = policy.act(states, goals, np.random.default_rng(seed))
            row = {"model": str(path), "method": policy.name, "set": name, "sampler": sampler, "pairs": len(states)}
            out.append(row | agreement(actions, expert))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--pairs", type=int, default=1000, help="held-out transitions per model")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    for path in args.models:
        for row in measure(path, args.pairs, args.seed):
            print(json.dumps(row))


if __name__ == "__main__":
    main()
