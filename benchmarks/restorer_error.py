"""How well a CDRB model's restorer R(tau_k, k) undoes the degradation at each k, and where sampling drifts.

For held-out demonstration windows tau_0 (the demos' validation episodes) and each k: tau_k = D(tau_0, k) with the
ends pinned, as in training. Reported per k, in normalized units: the degradation's error |tau_k - tau_0|^2, the
restorer's |R(tau_k, k) - tau_0|^2 (a trained restorer is below the degradation's at every k), and the share of
restored states in an obstacle. Then the sampler's own chain from random buffer states, run with all T - 1
restorations: after each one, the share of states in an obstacle and the mean distance of the iterate to the
nearest buffer state (what the restorer was trained on lies near the buffer; an iterate that leaves it is a
sampling-time input training never showed). Last, how many buffer states lie within 2 cm of a wall per task, next
to the demonstrations' share: coverage near the walls.

    python benchmarks/restorer_error.py --model runs/.../cdrb-s0.h5 --demos runs/.../demos.h5 --json out.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from cdrb_cli import artifacts
from cdrb_cli.envs.registry import family_of
from cdrb_cli.seeding import STREAM_TUNE
from cdrb_cli.stages.plan import load_planner


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--demos", type=Path, required=True)
    ap.add_argument("--windows", type=int, default=256, help="validation windows")
    ap.add_argument("--plans", type=int, default=100, help="sampling chains followed")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    model = artifacts.load(args.model, "model")
    demos = artifacts.load(args.demos, "demos")
    spec = model.manifest.env
    fam = family_of(spec)
    method = load_planner(model)
    norm = method.normalizer
    D = spec.obs_dim
    rng = np.random.default_rng(args.seed)

    def in_obstacle(z: torch.Tensor) -> float:
        x = norm.unnormalize(z[..., :D].detach().cpu().numpy())
        return float(fam.in_collision(spec, x).mean())

    windows = method.data(demos, norm, "valid").validation_batch(args.windows)
    tau0 = torch.from_numpy(windows)
    start, goal = method.ends(tau0, D)
    rows = []
    with torch.no_grad():
        for k in range(1, method.T):
            ks = np.full(len(tau0), k)
            tau_k = method.pin(method._degrade(tau0, ks, rng), start, goal)
            pred = method.pin(method.net(tau_k, torch.as_tensor(ks)), start, goal)
            rows.append(
                {
                    "k": k,
                    "eps_k": float(method.eps[k]),
                    "degraded_mse": float(torch.mean((tau_k - tau0) ** 2)),
                    "restored_mse": float(torch.mean((pred - tau0) ** 2)),
                    "restored_in_obstacle": in_obstacle(pred),
                }
            )
        # the sampler's chain: every restoration's x0 and the iterate it degrades to
        episodes = fam.draw_episodes(spec, args.plans, args.seed, STREAM_TUNE)
        s, g = fam.reset_states(spec, episodes)
        s_t = torch.as_tensor(norm.normalize(s), dtype=torch.float32)
        g_t = torch.as_tensor(norm.normalize(fam.goal_state(spec, g)), dtype=torch.float32)
        x = torch.from_numpy(method.ball.random_states((len(s), method.horizon), rng).astype(np.float32))
        x = method.pin(x, s_t, g_t)
        tree = cKDTree(method.points[:, :D])
        chain = []
        for k in range(method.T - 1, 0, -1):
            x0 = method.pin(method.net(x, torch.full((len(s),), k)), s_t, g_t)
            dist, _ = tree.query(x0[..., :D].reshape(-1, D).numpy())
            chain.append({"k": k, "x0_in_obstacle": in_obstacle(x0), "x0_buffer_distance": float(dist.mean())})
            x = method.pin(method._degrade(x0, np.full(len(s), k - 1), rng), s_t, g_t)
    # coverage near the walls: buffer states vs demonstration states within 2 cm of an obstacle
    near = {}
    if spec.obstacles is not None:
        pts = norm.unnormalize(method.points[:, :D].astype(np.float64))
        demo_states = demos.observations[rng.choice(len(demos.observations), 20000)]
        for name, states in (("buffer", pts), ("demos", demo_states)):
            grown = states.copy()
            hits = np.zeros(len(states), dtype=bool)
            for axis in range(3):
                for d in (-0.02, 0.02):
                    moved = grown.copy()
                    moved[:, axis] += d
                    hits |= fam.in_collision(spec, moved)
            near[name] = float(hits.mean())
    out = {"model": str(args.model), "env": spec.id, "T": method.T, "per_k": rows, "chain": chain, "near_wall": near}
    text = json.dumps(out, indent=1)
    if args.json:
        args.json.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
