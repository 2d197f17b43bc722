"""Environment ids -> EnvSpec. Stock ids: maze, maze-tight (the paper's), umaze, medium, large; any map file via
``--maze-map FILE`` (id ``map:<file stem>``)."""

from __future__ import annotations

import math
from pathlib import Path

from cdrb_cli.envs.maze import STOCK_LAYOUTS, MazeGeometry, load_map_file, stock_layout
from cdrb_cli.envs.spec import EnvSpec, MazeLayout
from cdrb_cli.errors import BadInput

# PointMaze physics (gymnasium-robotics): 100 Hz, ball radius 0.1 m, stock success radius 0.45 m.
POINTMAZE_DT = 0.01
BALL_RADIUS = 0.1
SUCCESS_RADIUS = 0.45
PLAN_STRIDE = 2

DESCRIPTIONS = {
    "maze": "CDRB Maze: 15x15, ring of walls with 3-cell gaps; centre starts, corner goals",
    "maze-tight": "CDRB Maze Tight: the same ring with 1-cell gaps",
    "umaze": "gymnasium-robotics U-maze (5x5)",
    "medium": "gymnasium-robotics medium maze (8x8), any free cell start/goal",
    "large": "gymnasium-robotics large maze (9x12), any free cell start/goal",
}

# The paper's two mazes use its plan length (168 planned states); at stride 2 that is 336 env steps, enough for the
# expert's slowest episodes (docs/environments.md).
_PAPER = {"maze": (168, 400), "maze-tight": (168, 400)}


def _timing_for(layout: MazeLayout) -> tuple[int, int]:
    """Default (horizon, episode_limit) for a layout, from its longest start->goal grid path: the scripted expert
    needs about 25 env steps per cell plus ~90 to accelerate and settle (measured on the stock maps)."""
    cells = MazeGeometry(layout).longest_start_goal_path()
    limit = int(math.ceil((120 + 28 * cells * layout.cell_size) / 50.0) * 50)
    horizon = int(math.ceil((limit - 40) / PLAN_STRIDE / 8.0) * 8)
    return horizon, limit


def maze_spec(env_id: str, layout: MazeLayout) -> EnvSpec:
    horizon, limit = _PAPER.get(env_id, None) or _timing_for(layout)
    geom = MazeGeometry(layout)
    return EnvSpec(
        id=env_id,
        family="pointmaze",
        obs_dim=4,
        action_dim=2,
        goal_dim=2,
        state_labels=["x", "y", "vx", "vy"],
        goal_dims=[0, 1],
        horizon=horizon,
        plan_stride=PLAN_STRIDE,
        episode_limit=limit,
        success_radius=SUCCESS_RADIUS,
        dt=POINTMAZE_DT,
        obstacles=geom.obstacles(BALL_RADIUS),
        maze=layout,
    )


def make_spec(env_id: str | None, maze_map: str | Path | None = None) -> EnvSpec:
    """The EnvSpec of a stock id, or of a map file (then ``env_id`` may be None or ``map``)."""
    if maze_map is not None:
        if env_id not in (None, "map", "custom"):
            raise BadInput(f"ENV {env_id!r} and --maze-map both given", hint="pass one of them (or ENV 'map')")
        layout = load_map_file(maze_map)
        return maze_spec(f"map:{layout.name}", layout)
    if env_id is None:
        raise BadInput("no environment given", hint=f"pass one of {', '.join(STOCK_LAYOUTS)} or --maze-map FILE")
    if env_id not in STOCK_LAYOUTS:
        raise BadInput(
            f"unknown environment {env_id!r}", hint=f"choose one of {', '.join(STOCK_LAYOUTS)}, or --maze-map FILE"
        )
    return maze_spec(env_id, stock_layout(env_id))


def list_envs() -> list[dict]:
    out = []
    for env_id in STOCK_LAYOUTS:
        s = make_spec(env_id)
        out.append(
            {
                "id": env_id,
                "description": DESCRIPTIONS[env_id],
                "obs_dim": s.obs_dim,
                "action_dim": s.action_dim,
                "goal_dim": s.goal_dim,
                "horizon": s.horizon,
                "plan_stride": s.plan_stride,
                "plan_env_steps": s.plan_env_steps,
                "episode_limit": s.episode_limit,
                "success_radius": s.success_radius,
                "starts": int(len(MazeGeometry(s.maze).start_cells)),
                "goals": int(len(MazeGeometry(s.maze).goal_cells)),
            }
        )
    return out
