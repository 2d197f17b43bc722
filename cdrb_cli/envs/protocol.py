"""The start/goal protocol shared by `plan --pairs` and `eval`: for a given seed, every method gets the same
pairs. A pair is a start cell drawn uniformly from the map's start cells and a different, reachable goal cell drawn
uniformly from its goal cells (for the paper's mazes: a central cell and a corner), then the stock reset noise."""

from __future__ import annotations

import numpy as np

from cdrb_cli.envs.pointmaze import PointMaze
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.seeding import STREAM_EVAL, episode_seeds


def draw_pairs(spec: EnvSpec, n: int, seed: int, stream: int = STREAM_EVAL):
    """[(episode_seed, start_cell, goal_cell)] for ``n`` episodes."""
    from cdrb_cli.envs.maze import MazeGeometry
    from cdrb_cli.stages.collect import draw_start_goal

    geom = MazeGeometry(spec.maze)
    out = []
    for s in episode_seeds(seed, n, stream):
        start, goal = draw_start_goal(geom, np.random.default_rng([int(s), 7]))
        out.append((int(s), start, goal))
    return out


def pair_states(spec: EnvSpec, pairs, env: PointMaze | None = None):
    """Start states (n, obs_dim) and goal positions (n, goal_dim) exactly as the environment resets them."""
    own = env is None
    env = env or PointMaze(spec)
    starts, goals = [], []
    for s, start_cell, goal_cell in pairs:
        obs, goal = env.reset(s, start_cell, goal_cell)
        starts.append(obs)
        goals.append(goal)
    if own:
        env.close()
    return np.array(starts), np.array(goals)


def goal_state(spec: EnvSpec, goal_xy: np.ndarray) -> np.ndarray:
    """The state a plan's goal is pinned to: the goal position at rest (zero velocity)."""
    goal_xy = np.atleast_2d(goal_xy)
    out = np.zeros((goal_xy.shape[0], spec.obs_dim))
    out[:, spec.goal_dims] = goal_xy
    return out
