"""`cdrb collect`: roll out an expert and write a `demos` artifact."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts, ui
from cdrb_cli.configs import CollectConfig, CollectSummary, PlannerExpertConfig, SacExpertConfig
from cdrb_cli.envs.maze import MazeGeometry, in_collision
from cdrb_cli.envs.pointmaze import PointMaze
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput, RunFailed
from cdrb_cli.seeding import STREAM_COLLECT, episode_seeds

_COMPASS = ["E", "NE", "N", "NW", "W", "SW", "S", "SE"]


def draw_start_goal(geom: MazeGeometry, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A start cell and a different, reachable goal cell, uniformly (the protocol shared by collect and eval)."""
    starts, goals = geom.start_cells, geom.goal_cells
    for _ in range(1000):
        s = starts[int(rng.integers(len(starts)))]
        g = goals[int(rng.integers(len(goals)))]
        if (s != g).any() and geom.bfs(g)[tuple(s)] >= 0:
            return s, g
    raise RunFailed("could not draw a start/goal pair: no goal cell is reachable from the start cells")


def exit_label(geom: MazeGeometry, states: np.ndarray) -> str:
    """The compass direction (from the start region's centre) of the first non-start cell an episode enters."""
    starts = {tuple(c) for c in geom.start_cells.tolist()}
    centre = geom.start_cells.mean(axis=0)
    for cell in geom.xy_to_cell(states[:, :2]):
        if tuple(cell.tolist()) not in starts:
            di, dj = cell - centre
            angle = np.arctan2(-di, dj)
            return _COMPASS[int(np.round(angle / (np.pi / 4))) % 8]
    return "none"


def rollout(env: PointMaze, expert, spec: EnvSpec, seed: int, start_cell, goal_cell, limit: int):
    """One episode: returns (states (T+1, obs), actions (T+1, act) with a zero last row, goal, success)."""
    rng = np.random.default_rng(seed)
    obs, goal = env.reset(seed, start_cell, goal_cell)
    expert.reset(obs[spec.goal_dims], goal, rng)
    states, actions = [obs], []
    success = np.linalg.norm(obs[spec.goal_dims] - goal) <= spec.success_radius
    for _ in range(limit):
        a = expert.act(obs)
        obs = env.step(a)
        actions.append(a)
        states.append(obs)
        success = success or np.linalg.norm(obs[spec.goal_dims] - goal) <= spec.success_radius
        if expert.settled(obs, goal):
            break
    actions.append(np.zeros(spec.action_dim))
    return np.array(states), np.array(actions), goal, bool(success)


def collect_config(
    spec: EnvSpec,
    episodes: int,
    seed: int = 0,
    expert: str = "planner",
    policy: Path | None = None,
    valid_fraction: float = 0.1,
) -> CollectConfig:
    if expert == "planner":
        expert_cfg = PlannerExpertConfig()
    else:
        if policy is None:
            raise BadInput("--expert sac needs --policy FILE", hint="train one with `cdrb expert train ENV`")
        if not Path(policy).is_file():
            raise BadInput(f"--policy {policy}: no such file", hint="train one with `cdrb expert train ENV`")
        expert_cfg = SacExpertConfig(
            policy_path=str(Path(policy).resolve()), policy_sha256=artifacts.sha256_file(policy)
        )
    return CollectConfig(env=spec.id, episodes=episodes, expert=expert_cfg, valid_fraction=valid_fraction, seed=seed)


def collect(spec: EnvSpec, config: CollectConfig, out: Path) -> artifacts.Demos:
    """Roll out the configured expert for ``config.episodes`` episodes and write the demos artifact to ``out``."""
    t0 = time.time()
    seed, episodes, valid_fraction = config.seed, config.episodes, config.valid_fraction
    env = PointMaze(spec)
    geom = env.geometry
    if config.expert.kind == "planner":
        from cdrb_cli.experts.maze_planner import MazeExpert

        agent = MazeExpert(spec, config.expert)
    else:
        from cdrb_cli.experts.sac import SacExpert

        agent = SacExpert(spec, config.expert.policy_path, deterministic=config.expert.deterministic)

    seeds = episode_seeds(seed, episodes, STREAM_COLLECT)
    all_states, all_actions, all_goals, starts, lengths, success = [], [], [], [], [], []
    routes: dict[str, dict[str, int]] = {}
    total = 0
    with ui.progress() as bar:
        task = bar.add_task(f"collect {spec.id}", total=episodes, info="")
        for e, ep_seed in enumerate(seeds):
            cell_rng = np.random.default_rng([int(ep_seed), 7])
            start_cell, goal_cell = draw_start_goal(geom, cell_rng)
            S, A, goal, ok = rollout(env, agent, spec, int(ep_seed), start_cell, goal_cell, spec.episode_limit)
            starts.append(total)
            lengths.append(len(S))
            total += len(S)
            all_states.append(S)
            all_actions.append(A)
            all_goals.append(np.repeat(goal[None], len(S), axis=0))
            success.append(ok)
            key = f"{int(goal_cell[0])},{int(goal_cell[1])}"
            label = exit_label(geom, S)
            routes.setdefault(key, {})
            routes[key][label] = routes[key].get(label, 0) + 1
            if e % 20 == 0 or e == episodes - 1:
                bar.update(task, completed=e + 1, info=f"success {np.mean(success):.1%}")
    env.close()
    observations = np.concatenate(all_states).astype(np.float32)
    in_walls = int(in_collision(observations, spec.obstacles).sum())
    split_rng = np.random.default_rng([seed, STREAM_COLLECT, 99])
    n_valid = int(round(valid_fraction * episodes))
    valid = np.zeros(episodes, dtype=bool)
    valid[split_rng.permutation(episodes)[:n_valid]] = True
    lengths_arr = np.array(lengths, dtype=np.int64)
    summary = CollectSummary(
        episodes=episodes,
        steps=int(total),
        success_rate=float(np.mean(success)),
        mean_length=float(lengths_arr.mean()),
        max_length=int(lengths_arr.max()),
        states_in_walls=in_walls,
        train_episodes=int((~valid).sum()),
        valid_episodes=int(valid.sum()),
        routes={k: dict(sorted(v.items())) for k, v in sorted(routes.items())},
        wall_time_s=round(time.time() - t0, 3),
    )
    manifest = artifacts.make_manifest("demos", env=spec, config=config, seed=seed, summary=summary)
    arrays = {
        "steps/observations": observations,
        "steps/actions": np.concatenate(all_actions).astype(np.float32),
        "steps/desired_goals": np.concatenate(all_goals).astype(np.float32),
        "episodes/start": np.array(starts, dtype=np.int64),
        "episodes/length": lengths_arr,
        "episodes/seed": seeds.astype(np.int64),
        "episodes/success": np.array(success, dtype=bool),
        "episodes/valid": valid,
    }
    artifacts.save(out, "demos", manifest, arrays)
    return artifacts.load(out, "demos")
