"""`cdrb eval`: plan once per episode, execute the plan with a controller in MuJoCo, and measure.

Protocol: for each evaluation seed, ``episodes`` start/goal pairs are drawn by :mod:`cdrb_cli.envs.protocol`
(start cell uniform over the map's start cells, goal cell uniform over its goal cells, stock reset noise), so
every method sees the same pairs for the same seed. Each episode: plan from the reset state to (goal, at rest),
execute the plan for ``spec.episode_limit`` environment steps (holding the goal after the plan ends), and record
success (within ``spec.success_radius`` at any step), steps to success, final distance, the fraction of planned
states inside walls, whether the executed path touched a wall, path length until success (also the scripted
expert's on the same reset, for the normalized path length) and planning time.
"""

from __future__ import annotations

import time

import numpy as np

from cdrb_cli import artifacts, ui
from cdrb_cli.configs import EvalConfig, EvalSummary, SeedResult
from cdrb_cli.envs.controllers import make_controller
from cdrb_cli.envs.maze import in_collision
from cdrb_cli.envs.pointmaze import PointMaze
from cdrb_cli.envs.protocol import draw_pairs, goal_state, pair_states
from cdrb_cli.seeding import STREAM_EVAL


def run_episode(env: PointMaze, spec, seed, start_cell, goal_cell, policy, steps: int):
    """Execute ``policy(obs, t) -> action`` from the seeded reset; returns per-episode measurements."""
    obs, goal = env.reset(seed, start_cell, goal_cell)
    states = [obs]
    for t in range(steps):
        obs = env.step(policy(obs, t))
        states.append(obs)
    S = np.array(states)
    dist = np.linalg.norm(S[:, spec.goal_dims] - goal[None], axis=1)
    hits = np.flatnonzero(dist <= spec.success_radius)
    first = int(hits[0]) if hits.size else None
    seg = np.linalg.norm(np.diff(S[:, :2], axis=0), axis=1)
    length = float(seg[: first if first is not None else len(seg)].sum())
    return {
        "success": first is not None,
        "steps": first if first is not None else steps,
        "final_distance": float(dist[-1]),
        "collision": bool(in_collision(S, spec.obstacles).any()),
        "path_length": length,
        "states": S,
    }


def expert_path_length(env, spec, seed, start_cell, goal_cell) -> float:
    from cdrb_cli.experts.maze_planner import MazeExpert

    expert = MazeExpert(spec)
    obs, goal = env.reset(seed, start_cell, goal_cell)
    expert.reset(obs[:2], goal, np.random.default_rng(seed))
    res = run_episode(env, spec, seed, start_cell, goal_cell, lambda o, t: expert.act(o), spec.episode_limit)
    return res["path_length"]


def evaluate(model, config: EvalConfig, out, device="cpu", keep_plans: bool = True, video_dir=None, videos: int = 0):
    from cdrb_cli.stages.plan import sample_plans
    from cdrb_cli.stages.train import load_planner

    t0 = time.time()
    spec = model.manifest.env
    method, ema = load_planner(model, device=device)
    net = ema if config.use_ema else method.net
    env = PointMaze(spec)
    ctrl = make_controller(
        config.controller, model.manifest.config.stride, env.dynamics, config.kp, config.kd, config.max_lag
    )
    steps = spec.episode_limit + config.extra_steps
    rows: dict[str, list] = {
        k: []
        for k in (
            "seed",
            "episode_seed",
            "success",
            "steps",
            "final_distance",
            "plan_in_wall_fraction",
            "executed_collision",
            "path_length",
            "expert_path_length",
            "plan_seconds",
            "start",
            "goal",
        )
    }
    all_plans, per_seed, executed = [], [], []
    total = len(config.seeds) * config.episodes
    with ui.progress() as bar:
        task = bar.add_task(f"eval {method.name}", total=total, info="")
        done = 0
        for seed in config.seeds:
            pairs = draw_pairs(spec, config.episodes, seed, STREAM_EVAL)
            starts, goals = pair_states(spec, pairs, env)
            plans, _, _, _, sec_batch = sample_plans(
                method,
                net,
                starts,
                goal_state(spec, goals),
                1,
                seed,
                config.sampler,
                config.sample_steps,
                batch_size=max(1, config.episodes),
                device=device,
            )
            sec_plan = sec_batch / len(plans)
            in_wall = in_collision(plans[..., : spec.obs_dim], spec.obstacles)
            ok_seed = []
            for e, (s, sc, gc) in enumerate(pairs):
                ctrl.reset(plans[e])
                res = run_episode(env, spec, s, sc, gc, ctrl.act, steps)
                rows["seed"].append(seed)
                rows["episode_seed"].append(s)
                rows["success"].append(res["success"])
                rows["steps"].append(res["steps"])
                rows["final_distance"].append(res["final_distance"])
                rows["plan_in_wall_fraction"].append(float(in_wall[e].mean()))
                rows["executed_collision"].append(res["collision"])
                rows["path_length"].append(res["path_length"])
                rows["expert_path_length"].append(expert_path_length(env, spec, s, sc, gc))
                rows["plan_seconds"].append(sec_plan)
                rows["start"].append(starts[e])
                rows["goal"].append(goals[e])
                if len(executed) < videos:
                    executed.append((plans[e], res["states"], goals[e], res["success"]))
                ok_seed.append(res["success"])
                done += 1
                bar.update(task, completed=done, info=f"success {np.mean(rows['success']):.1%}")
            all_plans.append(plans)
            idx = np.flatnonzero(np.array(rows["seed"]) == seed)
            per_seed.append(_seed_result(seed, rows, idx))
    env.close()
    arr = {f"episodes/{k}": np.asarray(v) for k, v in rows.items()}
    arr["episodes/start"] = np.asarray(rows["start"], dtype=np.float32)
    arr["episodes/goal"] = np.asarray(rows["goal"], dtype=np.float32)
    for k in ("final_distance", "plan_in_wall_fraction", "path_length", "expert_path_length", "plan_seconds"):
        arr[f"episodes/{k}"] = arr[f"episodes/{k}"].astype(np.float64)
    for k in ("seed", "episode_seed", "steps"):
        arr[f"episodes/{k}"] = arr[f"episodes/{k}"].astype(np.int64)
    for k in ("success", "executed_collision"):
        arr[f"episodes/{k}"] = arr[f"episodes/{k}"].astype(bool)
    if keep_plans:
        arr["plans"] = np.concatenate(all_plans).astype(np.float32)
    succ = np.array([p.success_rate for p in per_seed])
    wall = np.array([p.in_wall_fraction for p in per_seed])
    ratios = [p.path_length_ratio for p in per_seed if p.path_length_ratio is not None]
    summary = EvalSummary(
        method=method.name,
        model_preset=model.manifest.config.preset,
        success_mean=float(succ.mean()),
        success_std=float(succ.std()),
        in_wall_mean=float(wall.mean()),
        in_wall_std=float(wall.std()),
        executed_collision_mean=float(np.mean([p.executed_collision_rate for p in per_seed])),
        path_length_ratio_mean=float(np.mean(ratios)) if ratios else None,
        plan_seconds_mean=float(np.mean([p.plan_seconds for p in per_seed])),
        per_seed=per_seed,
        wall_time_s=round(time.time() - t0, 3),
    )
    manifest = artifacts.make_manifest(
        "eval", env=spec, config=config, seed=config.seed, parents=[model], summary=summary
    )
    artifacts.save(out, "eval", manifest, arr)
    if video_dir is not None and executed:
        from cdrb_cli.envs.render import rollout_gifs

        rollout_gifs(spec, executed, video_dir, label=method.name)
    return artifacts.load(out, "eval")


def _seed_result(seed: int, rows, idx) -> SeedResult:
    succ = np.array(rows["success"])[idx]
    ratio = np.array(rows["path_length"])[idx] / np.maximum(np.array(rows["expert_path_length"])[idx], 1e-9)
    return SeedResult(
        seed=int(seed),
        episodes=int(len(idx)),
        success_rate=float(succ.mean()),
        in_wall_fraction=float(np.mean(np.array(rows["plan_in_wall_fraction"])[idx])),
        executed_collision_rate=float(np.mean(np.array(rows["executed_collision"])[idx])),
        path_length_ratio=float(ratio[succ].mean()) if succ.any() else None,
        plan_seconds=float(np.mean(np.array(rows["plan_seconds"])[idx])),
    )
