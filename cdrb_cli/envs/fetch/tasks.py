"""The six Fetch tasks (and their "cross" variants): walls, home poses, and how starts and goals are drawn.

Walls follow the official CDRB code's obstacle files (``fetch_env/assets``) where they are consistent:

* push: a short wall, x in [1.22, 1.38], y in [0.728, 0.772] (official), 6 cm tall (official: 10 cm). While it
  pushes, the gripper's palm (12.8 cm wide) rides 7 cm above the table, so beside a 10 cm wall pushes near it
  collide: the scripted expert crosses 53.5% of crossing pairs with the official 10 cm wall, 97.5% at 6 cm
  (docs/environments.md). At 6 cm only the fingers can touch it, which keeps the official short wall's intent:
  the block cannot pass it, the gripper can;
* pick & place: a tall wall, centre (1.3, 0.75, 0.4), half size (0.15, 0.022, 0.3): top at z = 0.7;
* reach: two tall walls either side of the start, x in [1.15, 1.45], z in [0.17, 0.77] (the official check script's
  two walls; its shipped XML has one). The official walls leave a 13 cm corridor (y 0.705-0.835) for a gripper
  whose link is 12.8 cm wide, so nearly every state inside touches a wall (the scripted expert leaves it in 10% of
  episodes, 95% of its states in a wall); cdrb widens the corridor to 23 cm (walls at y = 0.749 +- 0.12), keeping
  "two walls either side of the start".

What the official code leaves open, chosen here (docs/environments.md):

* *Start*: every official wall runs through the stock start pose; the official env starts where the walls pushed the
  arm out during settling (:data:`OFFICIAL_START`). The gripper is driven to a *home* there (:data:`OBSTACLE_HOME`),
  clear of the walls: exactly the official start for Reach and Push; for Pick & Place 4.7 cm further past the
  tall wall's end (the official start rests against it).
* *Objects and goals* are drawn around the stock sampling centre (the stock start's x-y; +-0.15 m, as stock), the
  block at least 0.1 m from the home's x-y (stock rule), and redrawn while the block's or the goal's footprint
  (grown by ``wall_margin``) overlaps a wall, or (pick & place) the open gripper grasping the block there would
  come within 1.5 cm of a wall, or while a footprint comes within 3 cm of the table's edge (the stock range
  reaches 1.2 cm from the far edge, where a push that overshoots by that much drops the block). Reach goals
  are kept 2 cm above the table's reach of the gripper.
* *Cross* scenes (the Table-1 obstacle tasks) put the block and the goal on opposite sides of the wall (reach: the
  goal outside the corridor), so every episode must pass the wall.
* No goal lies within ``min_goal_distance`` (7 cm) of where the block (Reach: the gripper) starts, so no episode
  is won at reset.
* *From anywhere* (`--protocol anywhere`): the gripper starts at a point drawn as Reach draws its goals (the task's
  x-y range around the centre, the home's height +- the range, above the table, clear of every wall by
  ``wall_margin``), at least :data:`GRIP_BLOCK_CLEARANCE` from the block and ``min_goal_distance`` from a Reach
  goal; the environment drives it there at reset (:func:`draw_gripper_start`; the family keeps the draws whose arm
  touches no wall there).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.fetch.geometry import (
    BLOCK_HALF,
    GRIP_ABOVE_TABLE,
    MAX_OPENING,
    TABLE_TOP,
    TABLE_XY,
    Box,
    block_obstacles,
    gripper_obstacles,
)
from cdrb_cli.envs.geometry import in_boxes
from cdrb_cli.envs.spec import Scene

TaskName = Literal["reach", "push", "pick-place"]

#: the stock start of the grip site (gymnasium-robotics 1.4.2, measured after its settling steps)
STOCK_START = {
    "reach": (1.3419, 0.7491, 0.5347),
    "push": (1.3630, 0.7491, 0.4160),
    "pick-place": (1.3419, 0.7491, 0.5347),
}
#: pick & place: the grasping gripper's clearance from the walls at the block's start and goal, m
GRASP_MARGIN = 0.015
#: the block's centre height at rest on the table
BLOCK_Z = TABLE_TOP + BLOCK_HALF - 0.0001
#: from anywhere: the gripper starts at least this far from the block's centre (the open fingers clear it), m
GRIP_BLOCK_CLEARANCE = 0.1


class FetchScene(Scene):
    """A Fetch task: which stock env, its walls, the home pose and how starts and goals are drawn."""

    family: Literal["fetch"] = "fetch"
    task: TaskName
    walls: list[Box] = Field(default_factory=list, max_length=16)
    home: tuple[float, float, float] = Field(description="grip-site position every episode starts from")
    center: tuple[float, float] = Field(description="x-y centre around which blocks and goals are drawn")
    obj_range: float = Field(0.15, gt=0, le=0.5, description="blocks within +- this of the centre (x and y), m")
    target_range: float = Field(0.15, gt=0, le=0.5, description="goals within +- this of the centre, m")
    target_range_y: float | None = Field(None, gt=0, le=0.5, description="in y, if not target_range, m")
    air_fraction: float = Field(0.5, ge=0, le=1, description="pick & place: share of goals lifted into the air")
    air_height: float = Field(0.45, ge=0, le=0.6, description="pick & place: goals up to this far above the table")
    wall_margin: float = Field(0.035, ge=0, description="blocks and goals keep this far from every wall, m")
    edge_margin: float = Field(
        0.03, ge=0, le=0.2, description="block and goal footprints keep this far inside the table edge, m"
    )
    cross: bool = Field(False, description="block and goal on opposite sides of the wall (reach: goal outside)")
    extra_boxes: list[Box] = Field(
        default_factory=list,
        max_length=16,
        description="boxes put down after the data were collected (`--scene FILE` at plan and eval time): solid in "
        "the simulator and in every collision test, but not part of the task (the sides of the walls, the routes)",
    )
    change: str | None = Field(
        None, max_length=64, description="name of the scene change that put the extra boxes down (its file's stem)"
    )
    min_goal_distance: float = Field(
        0.07,
        ge=0,
        le=0.5,
        description="goals at least this far from where the block (Reach: the gripper) starts, m: no episode is won "
        "at reset (success is within 5 cm; 2 cm more for the block settling at reset)",
    )

    @property
    def solid(self) -> list[Box]:
        """Everything a body may not overlap: the task's walls and the boxes put down after training."""
        return [*self.walls, *self.extra_boxes]


def _tall(x=(1.15, 1.45), z=(0.17, 0.77), y=0.749, thick=0.005) -> Box:
    return Box(center=((x[0] + x[1]) / 2, y, (z[0] + z[1]) / 2), half=((x[1] - x[0]) / 2, thick, (z[1] - z[0]) / 2))


PUSH_WALL = Box(center=(1.3, 0.75, 0.43), half=(0.08, 0.022, 0.03))  # official: 10 cm tall (see above)
PICK_WALL = Box(center=(1.3, 0.75, 0.4), half=(0.15, 0.022, 0.3))
REACH_WALLS = [_tall(y=0.749 - 0.12), _tall(y=0.749 + 0.12)]  # official: a 13 cm corridor (see above)

#: the official start of the obstacle tasks: the stock start after the walls pushed the arm out during the stock
#: settling steps (measured with gymnasium-robotics 1.4.2)
OFFICIAL_START = {
    "reach": (1.3608, 0.7627, 0.5402),
    "push": (1.3978, 0.7489, 0.4161),
    "pick-place": (1.4629, 0.7489, 0.5450),
}
#: cdrb's start: the official one where it is clear of the walls (Reach, Push); Pick & Place's rests against the tall
#: wall's end and moves 4.7 cm further out in x: the gripper link clears the wall by 1.3 cm, room for the 8 mm the
#: expert's routes keep from a wall (at 1.50 m the expert succeeds in 97.5% of 200 episodes with 1,447 states in a
#: wall; at 1.51 m in 100% with none)
OBSTACLE_HOME = {
    "reach": OFFICIAL_START["reach"],
    "push": OFFICIAL_START["push"],
    "pick-place": (1.5100, 0.7489, 0.5450),
}


def scene_for(task: TaskName, obstacle: bool, cross: bool = False) -> FetchScene:
    sx, sy, sz = STOCK_START[task]
    walls: list[Box] = []
    home = (sx, sy, sz)
    if obstacle:
        walls = {"reach": REACH_WALLS, "push": [PUSH_WALL], "pick-place": [PICK_WALL]}[task]
        home = OBSTACLE_HOME[task]
    extra = {}
    if obstacle and task == "reach":  # goals on either side of the corridor need a wider y range
        extra = {"target_range_y": 0.30, "wall_margin": 0.02}
    if obstacle and task == "push":  # room for the pusher's fingers between the block and the wall
        extra = {"wall_margin": 0.045}
    return FetchScene(task=task, walls=walls, home=home, center=(sx, sy), cross=cross, **extra)


def side(scene: FetchScene, xyz: np.ndarray) -> int:
    """Which side of the walls a point is on: the sign of y - wall y (reach: 0 inside the corridor)."""
    if not scene.walls:
        return 0
    ys = sorted(w.center[1] for w in scene.walls)
    y = float(xyz[1])
    if len(ys) == 1:
        return 1 if y > ys[0] else -1
    return -1 if y < ys[0] else (1 if y > ys[-1] else 0)


def draw_task(scene: FetchScene, rng: np.random.Generator, tries: int = 10_000) -> tuple[tuple, tuple]:
    """One episode's (block x-y (empty for reach), goal x-y-z), drawn with ``rng`` by the rules above: the first of
    ``tries`` candidates that keeps them (RuntimeError when none does)."""
    attempt = _task_attempt(scene)
    for _ in range(tries):
        drawn = attempt(rng)
        if drawn is not None:
            return drawn
    raise RuntimeError(f"no start/goal drawn for the {scene.task} scene in {tries} tries")


#: the least share of candidate draws a scene must keep (:func:`task_draw_rate`): at 1%, a draw of 10,000 tries
#: fails with probability 0.99^10000 ~ 2e-44
MIN_DRAW_RATE = 0.01


def task_draw_rate(scene: FetchScene, n: int = 2000, seed: int = 0) -> float:
    """The share of ``n`` candidate (start, goal) draws that ``scene`` keeps: boxes that leave a task almost no room
    make :func:`draw_task` fail on some episode seeds and not others, so a scene is judged by the rate, not one draw."""
    attempt, rng = _task_attempt(scene), np.random.default_rng(seed)
    return sum(attempt(rng) is not None for _ in range(n)) / n


def _task_attempt(scene: FetchScene):
    """One candidate draw of the scene's task with a given ``rng``: the (block x-y, goal x-y-z) it keeps, or None."""
    cx, cy = scene.center
    home = np.asarray(scene.home)
    solid = scene.solid
    clear = block_obstacles(solid, dims=(0, 1, 2), margin=scene.wall_margin, rounded=False)
    # pick & place: the open gripper around the block (at its start and at its goal) keeps clear of the walls too
    grasp = gripper_obstacles(solid, MAX_OPENING, margin=GRASP_MARGIN) if scene.task == "pick-place" else None
    reach_clear = gripper_obstacles(solid, margin=scene.wall_margin)
    inset = BLOCK_HALF + scene.edge_margin
    (x0, x1), (y0, y1) = TABLE_XY

    def on_table(xy) -> bool:  # the footprint inside the table edge by edge_margin
        return bool(x0 + inset <= xy[0] <= x1 - inset and y0 + inset <= xy[1] <= y1 - inset)

    def attempt(rng: np.random.Generator):
        if scene.task == "reach":
            ry = scene.target_range_y or scene.target_range
            goal = np.array(
                [
                    cx + rng.uniform(-scene.target_range, scene.target_range),
                    cy + rng.uniform(-ry, ry),
                    scene.home[2] + rng.uniform(-scene.target_range, scene.target_range),
                ]
            )
            goal[2] = max(goal[2], TABLE_TOP + GRIP_ABOVE_TABLE + 0.02)
            if in_boxes(goal, reach_clear):
                return None
            if scene.cross and side(scene, goal) == 0:
                return None
            if np.linalg.norm(goal - home) < scene.min_goal_distance:
                return None
            return (), tuple(float(v) for v in goal)
        block = rng.uniform(-scene.obj_range, scene.obj_range, 2) + (cx, cy)
        if np.linalg.norm(block - home[:2]) < 0.1:
            return None
        block3 = np.array([block[0], block[1], BLOCK_Z])
        if not on_table(block):
            return None
        if in_boxes(block3, clear) or (grasp is not None and in_boxes(block3, grasp)):
            return None
        ry = scene.target_range_y or scene.target_range
        goal = np.array([cx + rng.uniform(-scene.target_range, scene.target_range), cy + rng.uniform(-ry, ry), BLOCK_Z])
        if scene.task == "pick-place" and rng.uniform() < scene.air_fraction:
            goal[2] += rng.uniform(0, scene.air_height)
        if not on_table(goal) or in_boxes(goal, clear) or (grasp is not None and in_boxes(goal, grasp)):
            return None
        if scene.cross and side(scene, goal) == side(scene, block3):
            return None
        if np.linalg.norm(goal - block3) < scene.min_goal_distance:
            return None
        return tuple(float(v) for v in block), tuple(float(v) for v in goal)

    return attempt


def draw_gripper_start(scene: FetchScene, rng: np.random.Generator, block, goal, tries: int = 10_000) -> tuple:
    """Where the gripper starts an episode drawn from anywhere (module docstring): a grip-site x-y-z, given the
    episode's block x-y (empty for Reach) and goal."""
    cx, cy = scene.center
    ry = scene.target_range_y or scene.target_range
    clear = gripper_obstacles(scene.solid, margin=scene.wall_margin)
    low = TABLE_TOP + GRIP_ABOVE_TABLE + 0.02
    block3 = None if len(block) == 0 else np.array([block[0], block[1], BLOCK_Z])
    for _ in range(tries):
        at = np.array(
            [
                cx + rng.uniform(-scene.target_range, scene.target_range),
                cy + rng.uniform(-ry, ry),
                max(scene.home[2] + rng.uniform(-scene.target_range, scene.target_range), low),
            ]
        )
        if in_boxes(at, clear):
            continue
        if block3 is not None and np.linalg.norm(at - block3) < GRIP_BLOCK_CLEARANCE:
            continue
        if block3 is None and np.linalg.norm(at - np.asarray(goal)) < scene.min_goal_distance:
            continue
        return tuple(float(v) for v in at)
    raise RuntimeError(f"no gripper start drawn for the {scene.task} scene in {tries} tries")


def split_start(task: str, start: tuple) -> tuple[tuple, tuple | None]:
    """An episode's start as (block x-y, or empty for Reach; grip-site x-y-z, or None at home): the block's x-y
    first, then the gripper's x-y-z when the episode starts it elsewhere than home."""
    n_block = 0 if task == "reach" else 2
    if len(start) not in (n_block, n_block + 3):
        raise ValueError(f"a {task} episode starts with {n_block} or {n_block + 3} numbers, got {len(start)}")
    return tuple(start[:n_block]), (tuple(start[n_block:]) or None)
