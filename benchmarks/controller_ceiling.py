"""How well each controller executes a *perfect* plan: the expert's own path, cut to the plan a model would make.

For every episode (tuning stream), the scripted expert runs from the episode's reset; its states at the env's plan
stride, cut to the horizon (and held at the last state when the episode is shorter), form the plan. The controller
then executes that plan from the same reset. Success and executed collisions here are the controller's ceiling:
a learned plan cannot do better through it. A plan that the horizon cuts before the goal counts against the
ceiling too, so the table also says whether the horizon fits the task.

    python benchmarks/controller_ceiling.py --envs fetch-reach,fetch-push --episodes 100 \
        --out docs/results/controller_ceiling.csv
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

from cdrb_cli.data import first_window
from cdrb_cli.envs.registry import CONTROLLERS, EXPERTS, family_of, make_spec
from cdrb_cli.errors import BadInput
from cdrb_cli.seeding import STREAM_TUNE
from cdrb_cli.stages.evaluate import run_episode

#: per family: (label, controller name, config overrides) of each controller setting measured; a controller that a
#: protocol prescribes runs under that protocol (its goal pin, episode length and early end)
SETTINGS = {
    "fetch": [
        ("official executor (official-code protocol)", "fetch-official", {}),
        ("track K=1", "fetch-track", {"gain": 1.0, "follow_block": False}),
        ("track K=2", "fetch-track", {"gain": 2.0, "follow_block": False}),
        ("track K=2, follow block", "fetch-track", {"gain": 2.0, "follow_block": True}),
        ("push along the block path", "fetch-push-path", {}),
        ("push along the block path, unstick 3", "fetch-push-path", {"unstick": 3}),
        ("push along the block path, corners 5 cm, unstick 3", "fetch-push-path", {"tolerance": 0.05, "unstick": 3}),
        ("push along the block path, corners 8 cm, unstick 3", "fetch-push-path", {"tolerance": 0.08, "unstick": 3}),
        ("push along the block path, corners 12 cm, unstick 3", "fetch-push-path", {"tolerance": 0.12, "unstick": 3}),
    ],
}


def measure(env_id: str, episodes: int, seed: int, horizon: int | None, stride: int | None) -> list[dict]:
    spec = make_spec(env_id)
    fam = family_of(spec)
    H = horizon or spec.horizon
    k = stride or spec.plan_stride
    entry = EXPERTS.get(fam.experts[0])
    expert = entry.build(spec, entry.configure(None))
    env = fam.make_env(spec)
    eps = fam.draw_episodes(spec, episodes, seed, STREAM_TUNE)
    rows = []
    try:
        plans, expert_ok, reached = [], [], []
        for ep in eps:
            obs, goal = env.reset(ep)
            expert.reset(obs, goal, np.random.default_rng(ep.seed))
            run = run_episode(env, spec, ep, lambda o, t: expert.act(o), spec.episode_limit)
            plan = first_window(run.states, H, k)  # as a training window from the episode's start
            plans.append(plan)
            expert_ok.append(run.success)
            reached.append(bool(fam.success(spec, plan, goal).any()))
        for label, name, overrides in SETTINGS[fam.name]:
            c = CONTROLLERS.get(name)
            cfg = c.config.model_validate({"name": name, **overrides})
            try:
                ctl = c.build(spec, env, cfg, k)
            except BadInput:  # not a controller for this task (e.g. fetch-push-path off Push)
                continue
            protocol = next((p for p in fam.protocols() if fam.protocol_controller(p) == name), fam.protocol)
            run_spec = fam.protocol_spec(spec, protocol)
            t0 = time.time()
            ok, coll = [], []
            for ep, plan in zip(eps, plans):
                ctl.reset(plan)
                run = run_episode(env, run_spec, ep, ctl.act, run_spec.episode_limit, lambda: ctl.finished)  # noqa: B023
                ok.append(run.success)
                coll.append(run.collision)
            rows.append(
                {
                    "env": env_id,
                    "horizon": H,
                    "stride": k,
                    "controller": label,
                    "episodes": len(eps),
                    "expert_success": round(100 * float(np.mean(expert_ok)), 1),
                    "plan_reaches_goal": round(100 * float(np.mean(reached)), 1),
                    "success": round(100 * float(np.mean(ok)), 1),
                    "executed_collisions": round(100 * float(np.mean(coll)), 1),
                    "seconds": round(time.time() - t0, 1),
                }
            )
            print(rows[-1], file=sys.stderr, flush=True)
    finally:
        env.close()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", required=True, help="comma-separated env ids")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0, help="tuning-stream seed of the episodes")
    ap.add_argument("--horizon", type=int, default=None, help="planned states (default: the env's)")
    ap.add_argument("--stride", type=int, default=None, help="env steps per planned state (default: the env's)")
    ap.add_argument("--out", type=Path, default=None, help="CSV to write (appends rows of other envs/settings)")
    args = ap.parse_args()
    rows = []
    for env_id in args.envs.split(","):
        rows += measure(env_id, args.episodes, args.seed, args.horizon, args.stride)
    if args.out:
        keep = []
        if args.out.exists():
            with args.out.open() as f:
                new = {(r["env"], r["horizon"], r["stride"], r["controller"]) for r in rows}
                keep = [
                    r
                    for r in csv.DictReader(f)
                    if (r["env"], int(r["horizon"]), int(r["stride"]), r["controller"]) not in new
                ]
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".tmp")
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(keep + rows)
        tmp.replace(args.out)
        print(args.out)


if __name__ == "__main__":
    main()
