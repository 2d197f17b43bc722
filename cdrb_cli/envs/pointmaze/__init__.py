"""The PointMaze family: gymnasium-robotics' PointMaze on any grid map.

Stock ids: ``maze`` and ``maze-tight`` (the paper's), ``umaze``, ``medium``, ``large`` (gymnasium-robotics'); any map
file through ``--maze-map FILE`` (id ``map:<file stem>``). The state is (x, y, vx, vy), the goal (x, y); a plan is
pinned to the whole start state and to the goal at rest. Protocol: a start cell drawn uniformly from the map's
start cells and a different, reachable goal cell from its goal cells, then the stock reset noise.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.family import EnvFamily, Episode
from cdrb_cli.envs.pointmaze.maze import (
    STOCK_LAYOUTS,
    MazeGeometry,
    MazeLayout,
    load_map_file,
    parse_map,
    stock_layout,
)
from cdrb_cli.envs.registry import FAMILIES
from cdrb_cli.envs.spec import EnvSpec, Scene
from cdrb_cli.errors import BadInput, NeedsScene
from cdrb_cli.seeding import episode_seeds

# PointMaze physics (gymnasium-robotics): 100 Hz, ball radius 0.1 m, stock success radius 0.45 m.
POINTMAZE_DT = 0.01
BALL_RADIUS = 0.1
SUCCESS_RADIUS = 0.45
OFFICIAL_SUCCESS_RADIUS = 0.55  # the official CDRB code's success test (info["success"])
MAX_SPEED = 5.0  # the env clips each velocity component at 5 m/s (before each step)
BALL_MASS = 4.0 / 3.0 * math.pi * BALL_RADIUS**3 * 1000.0  # kg: the stock ball (`PointMaze.dynamics` reads the same)
BALL_GEAR, BALL_DAMPING = 100.0, 1.0  # the stock actuator gear and joint damping
PLAN_STRIDE = 2

DESCRIPTIONS = {
    "maze": "CDRB Maze: 15x15, ring of walls with 3-cell gaps; centre starts, corner goals",
    "maze-tight": "CDRB Maze Tight: the same ring with 1-cell gaps",
    "umaze": "gymnasium-robotics U-maze (5x5)",
    "medium": "gymnasium-robotics medium maze (8x8), any free cell start/goal",
    "large": "gymnasium-robotics large maze (9x12), any free cell start/goal",
}
DISPLAY_NAMES = {"maze": "Maze", "maze-tight": "Maze Tight"}

# The paper's two mazes use its plan length (168 planned states); at stride 2 that is 336 env steps, enough for the
# expert's slowest episodes (docs/environments.md).
_PAPER = {"maze": (168, 400), "maze-tight": (168, 400)}


class PointMazeScene(Scene):
    """The maze map and the reset noise."""

    family: Literal["pointmaze"] = "pointmaze"
    maze: MazeLayout
    position_noise: float = Field(
        0.25, ge=0, description="uniform noise (per axis, in cells) added to start and goal cell centres at reset"
    )
    goal_noise: bool = Field(True, description="false: the goal is the exact cell centre (the official code's)")
    trained_maze: MazeLayout | None = Field(
        None,
        description="when plans run in another map than the model was trained in (`--maze-map` at plan/eval time): "
        "the training map; null: the same map",
    )


def _timing_for(layout: MazeLayout, anywhere: bool = False) -> tuple[int, int]:
    """Default (horizon, episode_limit) for a layout, from its longest start->goal grid path (``anywhere``: from any
    free cell): the scripted expert needs about 25 env steps per cell plus ~90 to accelerate and settle (measured on
    the stock maps)."""
    cells = MazeGeometry(layout).longest_start_goal_path(anywhere)
    limit = int(math.ceil((120 + 28 * cells * layout.cell_size) / 50.0) * 50)
    horizon = int(math.ceil((limit - 40) / PLAN_STRIDE / 8.0) * 8)
    return horizon, limit


def maze_spec(env_id: str, layout: MazeLayout) -> EnvSpec:
    horizon, limit = _PAPER.get(env_id, None) or _timing_for(layout)
    geom = MazeGeometry(layout)
    return EnvSpec(
        id=env_id,
        scene=PointMazeScene(maze=layout),
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
    )


#: the protocol (and demonstration start distribution) whose starts are any free cell
ANYWHERE = "anywhere"
#: the protocol of a changed map: pairs whose shortest path the new walls made longer
DETOUR = "detour"


class PointMazeFamily(EnvFamily):
    name = "pointmaze"
    scene_type = PointMazeScene
    experts = ("planner", "sac")
    expert_only_times_out = True
    controllers = ("pd", "inverse-dynamics", "waypoint")
    protocol = "centre-start/corner-goal"
    extra_protocols = {
        "official-code": "as the official CDRB code evaluates: the goal at the exact cell centre, success within "
        f"{OFFICIAL_SUCCESS_RADIUS} m, its executor (controller `waypoint`: <= 5 env steps per planned state)",
        ANYWHERE: "starts in any free cell from which the goal is reachable (at rest, the stock reset noise), goals "
        "the stock protocol's goal cells: plans from wherever the robot may be",
        DETOUR: "with --maze-map: the protocol's start and goal cells, only pairs whose shortest path in the new map "
        "is longer than in the training map (the new walls block the way the data went)",
    }
    start_protocols = (ANYWHERE,)
    scene_protocols = (DETOUR,)
    point_format = "x,y (at rest) or x,y,vx,vy, e.g. 0,0"
    # chosen by experiments/tune/obstacles-maze-tight.toml (Diffuser's choice routes through a buffer file it does
    # not carry: its best candidate without one)
    scene_avoid = {"cdrb": {"mask_buffer": True, "route_k": 8, "best_of": 4}, "diffuser": {"best_of": 4}}
    # chosen by experiments/tune/anywhere-maze-tight-look-ahead.toml (experiments/tuned/anywhere-maze-tight-replan.toml)
    replan_tuned = {
        "cdrb": {"controller.look_ahead": 2, "avoid.best_of": 8},
        "diffuser": {"controller.look_ahead": 4, "avoid.best_of": 8},
        "mlp": {"controller.look_ahead": 4},
    }
    # best-of chosen by experiments/tune/anywhere-maze-tight-best-of.toml (experiments/tuned/anywhere-maze-tight.toml);
    # CDRB's second try from a buffer route only touches pairs whose every sample crosses a wall: its k and the route
    # itself as a last resort chosen on tuning pairs of that kind
    # (docs/notebook/2026-11-29-hard-pairs-for-the-second-try.md); the first step counted in both choices, so a plan
    # starts where the robot is, and a plan that still leaps retimed along its own path
    # (docs/notebook/2026-11-29-plans-that-start-where-the-robot-is.md)
    start_tuned = {
        "cdrb": {
            "avoid.best_of": 16,
            "avoid.fallback_route_k": 4,
            "avoid.fallback_route_itself": True,
            "avoid.first_step": True,
            "avoid.retime": True,
        },
        "diffuser": {"avoid.best_of": 16},
    }

    # -------------------------------------------------------------- environments
    def env_ids(self) -> dict[str, str]:
        return {i: DESCRIPTIONS[i] for i in STOCK_LAYOUTS}

    def make_spec(self, env_id: str) -> EnvSpec:
        return maze_spec(env_id, stock_layout(env_id))

    def spec_from_file(self, path: Path) -> EnvSpec:
        layout = load_map_file(path)
        return maze_spec(f"map:{layout.name}", layout)

    def with_map(self, spec: EnvSpec, path: Path, flag: str = "--maze-map") -> EnvSpec:
        """The model's maze task in another map of the same size and cell size (walls added or moved); the spec's
        id becomes ``<id>+<map name>`` and its scene keeps the training map (``trained_maze``)."""
        if str(path).lower().endswith((".toml", ".json")):
            raise BadInput(
                f"{flag} {path}: a scene settings file, but {spec.id} is a maze",
                hint="pass a map text file: the training map with walls added (`cdrb envs --json` shows its rows)",
            )
        layout = load_map_file(path, flag)
        trained = spec.scene.trained_maze or spec.scene.maze
        if (layout.n_rows, layout.n_cols, layout.cell_size) != (trained.n_rows, trained.n_cols, trained.cell_size):
            raise BadInput(
                f"{flag} {path}: a {layout.n_rows}x{layout.n_cols} map, but the model was trained in a "
                f"{trained.n_rows}x{trained.n_cols} map (cell {trained.cell_size:g} m)",
                hint="draw the new walls into a copy of the training map (`cdrb envs --json` shows its rows)",
            )
        # the id of a spec already in another map is <id>+<map name>: its task's id is what precedes the map's name
        base = spec.id.removesuffix(f"+{spec.scene.maze.name}") if spec.scene.trained_maze is not None else spec.id
        scene = spec.scene.model_copy(update={"maze": layout, "trained_maze": trained})
        return spec.model_copy(
            update={
                "id": f"{base}+{layout.name}"[:200],
                "scene": scene,
                "obstacles": MazeGeometry(layout).obstacles(spec.obstacles.inflate),
            }
        )

    def scene_changed(self, spec: EnvSpec) -> bool:
        return spec.scene.trained_maze is not None

    def new_obstacle_crossings(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray | None:
        """Through a cell that is a wall here and was free in the training map (each such cell a box, the agent's
        radius around it)."""
        from cdrb_cli.envs.geometry import path_crosses_boxes
        from cdrb_cli.envs.spec import BoxObstacles

        trained = spec.scene.trained_maze
        if trained is None:
            return None
        here = MazeGeometry(spec.scene.maze)
        added = np.argwhere(~here.free & MazeGeometry(trained).free)
        if not len(added):
            return np.zeros(np.asarray(paths).shape[:-2], dtype=bool)
        boxes = BoxObstacles(
            dims=[0, 1],
            centers=[here.cell_to_xy(c).tolist() for c in added],
            half_sizes=[[here.s / 2, here.s / 2]] * len(added),
            inflate=spec.obstacles.inflate,
            low=[-1e3, -1e3],
            high=[1e3, 1e3],
        )
        return path_crosses_boxes(paths, boxes)

    def scene_change_warning(self, spec: EnvSpec) -> str | None:
        trained = spec.scene.trained_maze
        if trained is None:
            return None
        opened = MazeGeometry(spec.scene.maze).free & ~MazeGeometry(trained).free
        if not opened.any():
            return None
        cells = ", ".join(f"({i},{j})" for i, j in np.argwhere(opened)[:4])
        more = f" and {int(opened.sum()) - 4} more" if opened.sum() > 4 else ""
        return (
            f"{spec.scene.maze.name}: {int(opened.sum())} cell(s) free here were walls in training ({cells}{more}): "
            "the model has no data there, so plans will not use them"
        )

    def unconnected(self, spec: EnvSpec, starts: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Pairs whose cells lie in different free regions of the map (a point on a wall cell is not judged)."""
        geom = MazeGeometry(spec.scene.maze)
        label = np.pad(geom.components(), 1, constant_values=-1)  # a point off the map reads as a wall cell

        def region(points):
            cells = np.clip(geom.xy_to_cell(np.asarray(points)[..., :2]) + 1, 0, np.array(label.shape) - 1)
            return label[cells[..., 0], cells[..., 1]]

        a, b = region(starts), region(goals)
        return (a >= 0) & (b >= 0) & (a != b)

    def display_name(self, env_id: str) -> str:
        return DISPLAY_NAMES.get(env_id, env_id)

    def from_gym(self, gym_id: str, kwargs: dict, name: str) -> EnvSpec | None:
        """PointMaze_*: the walls of ``maze_map`` (the registered default when the kwargs omit it). A stock cdrb
        maze with the same walls is that maze (its start/goal cells are the protocol's); any other map becomes a
        layout of its own, every free cell a start and goal cell unless the map marks them (r, g, c)."""
        if not gym_id.startswith("PointMaze_"):
            return None
        from cdrb_cli.envs.pointmaze.env import CELL_CODES, import_gymnasium_robotics

        grid = kwargs.get("maze_map")
        if grid is None:
            gym = import_gymnasium_robotics()
            grid = gym.spec(gym_id).kwargs.get("maze_map")
        if grid is None:
            return None
        codes = {code: ch for ch, code in CELL_CODES.items()} | {"1": "#", "0": "."}  # maps may spell 0/1 as text
        try:
            rows = ["".join(codes[c] for c in row) for row in grid]
        except (KeyError, TypeError):
            raise BadInput(
                f"maze_map of {gym_id}: cells other than 0, 1, r, g, c", hint="not a PointMaze map"
            ) from None
        walls = [[ch == "#" for ch in r] for r in rows]
        for env_id in STOCK_LAYOUTS:
            stock = stock_layout(env_id)
            if [[ch == "#" for ch in r] for r in stock.rows] == walls:
                return self.make_spec(env_id)
        if not any(ch in "SGC" for r in rows for ch in r):
            rows = [r.replace(".", "C") for r in rows]
        return maze_spec(f"map:{name}", parse_map("\n".join(rows), name=name, source=f"{gym_id} maze_map"))

    def to_gym(self, spec: EnvSpec):
        """PointMaze_UMaze-v3 made with this maze's map, as cdrb runs it (continuing task, fixed target)."""
        import dataclasses

        from cdrb_cli.envs.pointmaze.env import import_gymnasium_robotics, maze_map

        base = import_gymnasium_robotics().spec("PointMaze_UMaze-v3")
        kwargs = {**base.kwargs, "maze_map": maze_map(spec), "continuing_task": True, "reset_target": False}
        return dataclasses.replace(base, kwargs=kwargs, max_episode_steps=spec.episode_limit)

    def details(self, spec: EnvSpec) -> dict[str, Any]:
        g = MazeGeometry(spec.scene.maze)
        # the rows too: a new scene for a trained model is a copy of its map with walls drawn in
        return {"starts": int(len(g.start_cells)), "goals": int(len(g.goal_cells)), "rows": list(spec.scene.maze.rows)}

    def make_env(self, spec: EnvSpec):
        from cdrb_cli.envs.pointmaze.env import PointMaze

        return PointMaze(spec)

    def make_gym_env(self, spec: EnvSpec, seed: int):
        from cdrb_cli.envs.pointmaze.env import training_env

        return training_env(spec, seed)

    # -------------------------------------------------------------- protocol
    def protocol_spec(self, spec: EnvSpec, protocol: str) -> EnvSpec:
        if protocol == ANYWHERE and spec.id.partition("+")[0] not in _PAPER:
            # a limit sized from the map's start cells is short for a start in its farthest free cell; the stock
            # maps keep the paper's fixed limit, which their starts from anywhere meet (in a scene too: <id>+<map>)
            limit = _timing_for(spec.scene.maze, anywhere=True)[1]
            return spec.model_copy(update={"episode_limit": max(spec.episode_limit, limit)})
        if protocol != "official-code":
            return spec
        scene = spec.scene.model_copy(update={"goal_noise": False})
        # the official executor may spend up to 5 env steps per planned state and 20 on the last one
        limit = max(spec.episode_limit, 5 * (spec.horizon - 1) + 20)
        return spec.model_copy(
            update={"scene": scene, "success_radius": OFFICIAL_SUCCESS_RADIUS, "episode_limit": limit}
        )

    def protocol_controller(self, protocol: str) -> str | None:
        return "waypoint" if protocol == "official-code" else None

    def draw_episodes(self, spec: EnvSpec, n: int, seed: int, stream: int) -> list[Episode]:
        return self.draw_protocol_episodes(spec, n, seed, stream)

    def draw_protocol_episodes(
        self, spec: EnvSpec, n: int, seed: int, stream: int, protocol: str | None = None
    ) -> list[Episode]:
        """Each episode's start and goal cells from its own seed; ``anywhere`` draws starts over every free cell
        (its own generator key, so its pairs are not the stock pairs moved)."""
        geom = MazeGeometry(spec.scene.maze)
        if protocol == DETOUR:
            return self._detour_episodes(spec, geom, n, seed, stream)
        anywhere = protocol == ANYWHERE
        out = []
        for s in episode_seeds(seed, n, stream):
            rng = np.random.default_rng([int(s), 11 if anywhere else 7])
            start, goal = geom.draw_start_goal(rng, anywhere=anywhere)
            out.append(Episode(int(s), tuple(int(v) for v in start), tuple(int(v) for v in goal)))
        return out

    def _detour_episodes(self, spec: EnvSpec, geom: MazeGeometry, n: int, seed: int, stream: int) -> list[Episode]:
        """Episodes whose start/goal pair is drawn uniformly from the pairs the new map makes longer."""
        if spec.scene.trained_maze is None:
            raise NeedsScene(
                f"protocol {DETOUR}: {spec.id} runs in the map it was trained in, so no pair needs a detour",
                need="the training map with walls added",
                flag="--maze-map",
            )
        pairs = geom.detour_pairs(MazeGeometry(spec.scene.trained_maze))
        if not len(pairs):
            raise BadInput(
                f"protocol {DETOUR}: the walls of {spec.scene.maze.name} lengthen no start-to-goal path",
                hint="close a passage the protocol's pairs use, or use the stock protocol",
            )
        out = []
        for s in episode_seeds(seed, n, stream):
            pair = pairs[int(np.random.default_rng([int(s), 13]).integers(len(pairs)))]
            out.append(Episode(int(s), tuple(int(v) for v in pair[:2]), tuple(int(v) for v in pair[2:])))
        return out

    def check_point(self, spec: EnvSpec, state: np.ndarray, flag: str) -> None:
        ob = spec.obstacles
        pos = state[ob.dims]
        text = ",".join(f"{v:g}" for v in pos)
        if np.any(pos < np.asarray(ob.low)) or np.any(pos > np.asarray(ob.high)):
            raise BadInput(
                f"{flag} {text}: outside the map "
                f"(x in [{ob.low[0]:g}, {ob.high[0]:g}], y in [{ob.low[1]:g}, {ob.high[1]:g}])",
                hint="choose a point inside the maze",
            )
        speed = np.abs(state[2:4])
        if np.any(speed > MAX_SPEED):
            raise BadInput(
                f"{flag} {','.join(f'{v:g}' for v in state)}: a velocity beyond the ball's {MAX_SPEED:g} m/s per axis",
                hint="give x,y (at rest) or a velocity within the limit",
            )
        if self.in_collision(spec, state[None])[0]:
            raise BadInput(
                f"{flag} {text}: inside a wall (the agent, radius {ob.inflate:g}, overlaps it)",
                hint="choose a free point (`cdrb collect --plot` shows the map)",
            )

    # -------------------------------------------------------------- geometry
    def route(self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray) -> tuple[str, str]:
        geom = MazeGeometry(spec.scene.maze)
        cell = geom.xy_to_cell(goal)
        return f"{int(cell[0])},{int(cell[1])}", geom.exit_label(states)

    def off_protocol_starts(self, spec: EnvSpec, starts: np.ndarray) -> np.ndarray:
        """Starts whose cell is not one of the map's start cells (``S`` or ``C``)."""
        geom = MazeGeometry(spec.scene.maze)
        cells = geom.xy_to_cell(np.asarray(starts)[:, :2])
        return ~(cells[:, None, :] == geom.start_cells[None]).all(-1).any(-1)

    def max_step(self, spec: EnvSpec) -> float:
        # the env clips each velocity component at MAX_SPEED *before* a step, then one Euler step with the full
        # force adds h (gear - damping MAX_SPEED) / (mass + h damping) to it, and moves the ball by h v'
        h = spec.dt
        v = MAX_SPEED + h * (BALL_GEAR - BALL_DAMPING * MAX_SPEED) / (BALL_MASS + h * BALL_DAMPING)
        return math.sqrt(2.0) * v * h

    # -------------------------------------------------------------- pictures
    def speed(self, spec: EnvSpec, states: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(states)[..., 2:4], axis=-1)

    def goal_group(self, spec: EnvSpec, goal: np.ndarray) -> int:
        g = MazeGeometry(spec.scene.maze)
        goals = g.cell_to_xy(g.goal_cells)
        return int(np.argmin(np.linalg.norm(goals - np.asarray(goal)[None, :2], axis=1)))

    def draw_scene(self, ax, spec: EnvSpec) -> None:
        from cdrb_cli.envs.pointmaze.render import draw_maze

        draw_maze(ax, spec)

    def render_frames(
        self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray, every: int, plan: np.ndarray | None = None
    ) -> list[np.ndarray]:
        from cdrb_cli.envs.pointmaze.render import mujoco_frames

        return mujoco_frames(spec, states, goal, every, plan=plan)


FAMILIES.register(PointMazeFamily())
