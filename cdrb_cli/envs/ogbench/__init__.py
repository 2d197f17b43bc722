"""The OGBench family: OGBench's PointMaze tasks (Park et al., ICLR 2025), medium, large and giant, with the data of
its ``navigate`` and ``stitch`` datasets generated here by its documented procedure.

Env ids are OGBench's dataset names, e.g. ``pointmaze-medium-navigate-v0``: the maze, and the data `cdrb collect`
makes for it. The state and the goal are the position (x, y) in OGBench's coordinates; the agent moves by up to 0.2 m
per axis per step (docs/environments.md). Evaluation is OGBench's: its five tasks per maze (start and goal cells, each
with U(-1, 1) m of noise), episode i running task i mod 5, success within 1 m of the goal, 1,000 steps. Collection
(the collect stream) draws OGBench's data episodes instead: ``navigate``, a start in any free cell and a goal in a
vertex cell, 1,000 steps (giant: 2,000) with the goal re-drawn on each success; ``stitch``, a start in any free cell
and a goal exactly 4 cells away, 200 steps.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import numpy as np

from cdrb_cli.envs.family import EnvFamily, Episode
from cdrb_cli.envs.ogbench.env import ACTION_SCALE, AGENT_RADIUS, FRAME_SKIP, TIMESTEP
from cdrb_cli.envs.ogbench.maze import MAPS, TASKS, OGBenchGeometry, layout
from cdrb_cli.envs.pointmaze.maze import MazeLayout
from cdrb_cli.envs.registry import FAMILIES
from cdrb_cli.envs.spec import EnvSpec, Scene
from cdrb_cli.errors import BadInput
from cdrb_cli.seeding import STREAM_COLLECT, episode_seeds

SUCCESS_RADIUS = 1.0
EPISODE_LIMIT = 1000
PLAN_STRIDE = 4
DATASETS = ("navigate", "stitch")
#: steps per collected episode: OGBench's max_episode_steps less the row its loader drops
COLLECT_STEPS = {("navigate", "giant"): 2000, ("navigate", None): 1000, ("stitch", None): 200}
#: stitch data: the goal is this many cells (by grid distance) from the start
STITCH_CELLS = 4
#: the collision test's agent radius: MuJoCo's soft contacts let the 0.7 m sphere press up to ~4 cm into a wall it
#: is pushed against, so a state counts as in a wall only when deeper than 5 cm
COLLISION_RADIUS = AGENT_RADIUS - 0.05


class OGBenchScene(Scene):
    """The maze and the kind of data collected in it."""

    family: Literal["ogbench"] = "ogbench"
    maze: MazeLayout
    maze_name: Literal["medium", "large", "giant"]
    dataset: Literal["navigate", "stitch"]


def env_id(maze: str, dataset: str) -> str:
    return f"pointmaze-{maze}-{dataset}-v0"


def _horizon(maze: str) -> int:
    """Planned states for the maze's longest task: about 25 steps per cell along the grid path plus 50, at the
    plan stride, rounded up to a multiple of 8."""
    g = OGBenchGeometry(layout(maze))
    cells = max(int(g.bfs(goal)[start]) for start, goal in TASKS[maze])
    return int(math.ceil((25 * cells + 50) / PLAN_STRIDE / 8.0) * 8)


def ogbench_spec(maze: str, dataset: str) -> EnvSpec:
    maze_layout = layout(maze)
    return EnvSpec(
        id=env_id(maze, dataset),
        scene=OGBenchScene(maze=maze_layout, maze_name=maze, dataset=dataset),
        obs_dim=2,
        action_dim=2,
        goal_dim=2,
        state_labels=["x", "y"],
        goal_dims=[0, 1],
        horizon=_horizon(maze),
        plan_stride=PLAN_STRIDE,
        episode_limit=EPISODE_LIMIT,
        success_radius=SUCCESS_RADIUS,
        dt=TIMESTEP * FRAME_SKIP,
        obstacles=OGBenchGeometry(maze_layout).obstacles(COLLISION_RADIUS),
    )


class OGBenchFamily(EnvFamily):
    name = "ogbench"
    scene_type = OGBenchScene
    experts = ("ogbench-noisy",)
    controllers = ("pursuit",)
    protocol = "ogbench-tasks"
    point_format = "x,y in OGBench's coordinates (cell (i, j) at 4j-4, 4i-4), e.g. 0,0"

    def env_ids(self) -> dict[str, str]:
        return {
            env_id(m, d): f"OGBench PointMaze {m} ({len(MAPS[m][0])}x{len(MAPS[m])} cells of 4 m), {d} data"
            for m in MAPS
            for d in DATASETS
        }

    def make_spec(self, env_id: str) -> EnvSpec:
        parts = env_id.split("-")
        if len(parts) != 4 or parts[0] != "pointmaze" or parts[1] not in MAPS or parts[2] not in DATASETS:
            raise BadInput(f"{env_id!r}: not an OGBench PointMaze id", hint="see `cdrb envs`")
        return ogbench_spec(parts[1], parts[2])

    def details(self, spec: EnvSpec) -> dict[str, Any]:
        return {"tasks": [[list(s), list(g)] for s, g in TASKS[spec.scene.maze_name]], "dataset": spec.scene.dataset}

    def make_env(self, spec: EnvSpec):
        from cdrb_cli.envs.ogbench.env import PointMazeOG

        return PointMazeOG(spec)

    def collect_limit(self, spec: EnvSpec) -> int:
        key = (spec.scene.dataset, spec.scene.maze_name)
        return COLLECT_STEPS.get(key, COLLECT_STEPS[(spec.scene.dataset, None)])

    def draw_episodes(self, spec: EnvSpec, n: int, seed: int, stream: int) -> list[Episode]:
        """The collect stream draws OGBench's data episodes (``navigate`` or ``stitch``, as the spec's dataset);
        every other stream runs OGBench's five evaluation tasks in turn, episode i task i mod 5."""
        g = OGBenchGeometry(spec.scene.maze)
        seeds = episode_seeds(seed, n, stream)
        if stream != STREAM_COLLECT:
            tasks = TASKS[spec.scene.maze_name]
            return [Episode(int(s), tasks[i % 5][0], tasks[i % 5][1]) for i, s in enumerate(seeds)]
        cells, out = np.argwhere(g.free), []
        for s in seeds:
            rng = np.random.default_rng([int(s), 13])
            start = tuple(int(v) for v in cells[int(rng.integers(len(cells)))])
            if spec.scene.dataset == "navigate":
                goals = g.vertex_cells
            else:
                goals = np.argwhere(g.bfs_from(start) == STITCH_CELLS)
                goals = goals if len(goals) else np.asarray([start])
            goal = tuple(int(v) for v in goals[int(rng.integers(len(goals)))])
            out.append(Episode(int(s), start, goal))
        return out

    def dataset_env(self, path: Path) -> str | None:
        from cdrb_cli.envs.ogbench.dataset import env_for

        return env_for(path)

    def read_dataset(self, spec: EnvSpec, path: Path):
        from cdrb_cli.envs.ogbench.dataset import read_episodes

        return read_episodes(spec, path)

    def max_step(self, spec: EnvSpec) -> float:
        return math.sqrt(2.0) * ACTION_SCALE

    def draw_scene(self, ax, spec: EnvSpec) -> None:
        super().draw_scene(ax, spec)
        g = OGBenchGeometry(spec.scene.maze)
        for k, (s, goal) in enumerate(TASKS[spec.scene.maze_name], start=1):
            (sx, sy), (gx, gy) = g.cell_to_xy(s), g.cell_to_xy(goal)
            ax.annotate(f"{k}", (gx, gy), ha="center", va="center", fontsize=7, color="#b22222", zorder=3)
            ax.plot([sx], [sy], "o", ms=3, color="#1f77b4", zorder=3)


FAMILIES.register(OGBenchFamily())
