"""The Fetch family: gymnasium-robotics' Fetch Reach, Push and Pick & Place, each with and without walls.

Ids: ``fetch-reach``, ``fetch-push``, ``fetch-pick-place`` and their ``-obstacle`` variants (the paper's six Fetch
rows: every pair must get past the wall), plus ``-obstacle-mixed`` variants whose goals may lie on either side.
The state is the stock observation (10-D for Reach, 25-D with a block; docs/environments.md lists the entries),
the goal the grip site's (Reach) or the block's position; success is within 5 cm (stock). Walls are MuJoCo geoms
(:mod:`cdrb_cli.envs.fetch.env`); the collision test covers the gripper and the block with their extents
(:mod:`cdrb_cli.envs.fetch.geometry`); starts and goals are drawn by :mod:`cdrb_cli.envs.fetch.tasks`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cdrb_cli.envs.family import EnvFamily, Episode
from cdrb_cli.envs.fetch.geometry import (
    block_obstacles,
    body_obstacles,
    paths_in_obstacles,
    paths_in_obstacles_by_body,
    states_in_obstacles,
    states_in_obstacles_by_body,
)
from cdrb_cli.envs.fetch.tasks import BLOCK_Z, FetchScene, draw_gripper_start, draw_task, scene_for, side
from cdrb_cli.envs.geometry import path_crosses_boxes
from cdrb_cli.envs.registry import FAMILIES
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput, NeedsScene
from cdrb_cli.seeding import episode_seeds

#: the protocol of a changed scene: pairs whose shortest route the boxes put down block
DETOUR = "detour"
#: the protocol whose gripper starts anywhere in the workspace (tasks.draw_gripper_start)
ANYWHERE = "anywhere"
#: a gripper start is drawn again at most this many times while the arm touches a wall there
ANYWHERE_TRIES = 50
#: a detour draw gives up when fewer than one in this many candidate pairs needs a detour
DETOUR_SCAN = 200
FETCH_DT = 0.04  # 20 substeps x 2 ms
SUCCESS_RADIUS = 0.05  # stock distance_threshold
MAX_DELTA = 0.05  # the mocap moves at most this far per axis per step
#: the most a velocity of a full state may be, per axis: the observation gives a velocity as the motion over one
#: step (m or rad per :data:`FETCH_DT`), and the arm moves at most :data:`MAX_DELTA` a step; ten times that
#: leaves room for a knocked block and refuses a typo (9999 m/s)
MAX_STEP_MOTION = 0.5
MOVED = 0.02  # a block that never moved this far from its start was never grasped or pushed (failure cause "grasp")

REACH_LABELS = ["grip_x", "grip_y", "grip_z", "finger_l", "finger_r", "grip_vx", "grip_vy", "grip_vz"]
REACH_LABELS += ["finger_vl", "finger_vr"]
OBJECT_LABELS = ["grip_x", "grip_y", "grip_z", "block_x", "block_y", "block_z", "rel_x", "rel_y", "rel_z"]
OBJECT_LABELS += ["finger_l", "finger_r", "block_roll", "block_pitch", "block_yaw", "block_vx", "block_vy", "block_vz"]
OBJECT_LABELS += ["block_wx", "block_wy", "block_wz", "grip_vx", "grip_vy", "grip_vz", "finger_vl", "finger_vr"]

#: id -> (task, obstacle, cross, horizon, episode length, description). Horizons follow the official code's
#: (Reach 28, Push/Pick 36, Push and Pick & Place obstacle tasks 56 planned states); episodes are fixed-length, the
#: expert holding at the goal once there. The Table-1 obstacle tasks draw only pairs that must get past the wall;
#: the ``-mixed`` ids keep the draw with both sides allowed.
TASKS: dict[str, tuple[str, bool, bool, int, int, str]] = {
    "fetch-reach": ("reach", False, False, 28, 50, "Fetch Reach: move the gripper to a point"),
    "fetch-push": ("push", False, False, 36, 50, "Fetch Push: push a block to a point on the table"),
    "fetch-pick-place": ("pick-place", False, False, 36, 50, "Fetch Pick & Place: carry a block to a point"),
    "fetch-reach-obstacle": ("reach", True, True, 28, 80, "Fetch Reach out of a corridor of two tall walls"),
    "fetch-push-obstacle": ("push", True, True, 56, 100, "Fetch Push past a short wall, to its other side"),
    "fetch-pick-place-obstacle": ("pick-place", True, True, 56, 100, "Fetch Pick & Place over or around a tall wall"),
    "fetch-reach-obstacle-mixed": ("reach", True, False, 28, 80, "Reach obstacle, goals inside the corridor too"),
    "fetch-push-obstacle-mixed": ("push", True, False, 56, 100, "Push obstacle, goals on either side of the wall"),
    "fetch-pick-place-obstacle-mixed": ("pick-place", True, False, 56, 100, "Pick obstacle, goals on either side"),
}
#: env steps per planned state where 1 is too short for the expert's path: the scripted pusher takes up to 90 steps
#: around the short wall (p90 66 > 56), reaching out of the corridor up to 48 (> 28 planned states), and from the
#: official start a carry over or around the tall wall reaches its goal within 56 steps in 67% of episodes only;
#: the expert's cut-plan ceilings are in docs/benchmarks.md §6.1
STRIDES = {
    "fetch-push-obstacle": 2,
    "fetch-push-obstacle-mixed": 2,
    "fetch-reach-obstacle": 2,
    "fetch-reach-obstacle-mixed": 2,
    "fetch-pick-place-obstacle": 2,
    "fetch-pick-place-obstacle-mixed": 2,
}
DISPLAY_NAMES = {
    "fetch-reach": "Reach",
    "fetch-push": "Push",
    "fetch-pick-place": "Pick & Place",
    "fetch-reach-obstacle": "Reach Obstacle",
    "fetch-push-obstacle": "Push Obstacle",
    "fetch-pick-place-obstacle": "Pick & Place Obstacle",
}


def fetch_spec(env_id: str) -> EnvSpec:
    task, obstacle, cross, horizon, limit, _ = TASKS[env_id]
    scene = scene_for(task, obstacle, cross)
    with_block = task != "reach"
    goal_dims = [3, 4, 5] if with_block else [0, 1, 2]
    return EnvSpec(
        id=env_id,
        scene=scene,
        obs_dim=25 if with_block else 10,
        action_dim=4,
        goal_dim=3,
        state_labels=OBJECT_LABELS if with_block else REACH_LABELS,
        goal_dims=goal_dims,
        # the official code pins state dims 0:6 (gripper and block positions) at the start; at the goal only the
        # goal's own dims are known (where the gripper ends up is the plan's business)
        pinned_dims=[0, 1, 2, 3, 4, 5] if with_block else [0, 1, 2],
        pinned_end_dims=goal_dims,
        horizon=horizon,
        plan_stride=STRIDES.get(env_id, 1),
        episode_limit=limit,
        success_radius=SUCCESS_RADIUS,
        dt=FETCH_DT,
        obstacles=body_obstacles(scene.walls, task)[0],
    )


def has_object(spec: EnvSpec) -> bool:
    return spec.scene.task != "reach"


class FetchFamily(EnvFamily):
    name = "fetch"
    scene_type = FetchScene
    experts = ("fetch-scripted", "sac")
    controllers = ("fetch-track", "fetch-push-path", "fetch-official")
    protocol = "stock-centre draws, walls rejected"
    extra_protocols = {
        "official-code": "as the official CDRB code evaluates: its executor (controller `fetch-official`: a step "
        "budget per planned state, a 1 cm gate, its pick and push rules), the gripper pinned to the goal with the "
        "block, success at any step until the plan runs out",
        DETOUR: "with --scene: the stock draws (never inside a new box), only pairs whose shortest route in the "
        "training scene a new box blocks (the way the data went is closed)",
        ANYWHERE: "the stock block and goal draws, the gripper starting anywhere in the workspace (drawn as Reach "
        "draws its goals, clear of the walls and the block, and where the whole arm touches no wall), at rest: "
        "plans from wherever the robot may be",
    }
    start_protocols = (ANYWHERE,)
    scene_protocols = (DETOUR,)
    # chosen by experiments/tune/obstacles-fetch-reach-obstacle.toml (Diffuser's choice routes through a buffer
    # file it does not carry: its best candidate without one)
    scene_avoid = {"cdrb": {"mask_buffer": True, "route_k": 2, "best_of": 4}, "diffuser": {"best_of": 4}}
    point_format = "--goal x,y,z; --start the block's x,y (gripper at home) or, for Reach, the gripper's x,y,z"

    # -------------------------------------------------------------- environments
    def env_ids(self) -> dict[str, str]:
        return {i: t[-1] for i, t in TASKS.items()}

    def make_spec(self, env_id: str) -> EnvSpec:
        return fetch_spec(env_id)

    def display_name(self, env_id: str) -> str:
        return DISPLAY_NAMES.get(env_id, env_id)

    #: gymnasium-robotics' Fetch task names and cdrb's environments without walls (same state layout)
    GYM_TASKS = {"Reach": "fetch-reach", "Push": "fetch-push", "PickAndPlace": "fetch-pick-place"}

    def from_gym(self, gym_id: str, kwargs: dict, name: str) -> EnvSpec | None:
        import re

        m = re.fullmatch(r"Fetch(Reach|Push|PickAndPlace)(Dense)?-v\d+", gym_id)
        return self.make_spec(self.GYM_TASKS[m.group(1)]) if m else None

    def to_gym(self, spec: EnvSpec):
        if spec.scene.walls:  # cdrb's tasks with walls exist in no gymnasium registry
            return None
        task = {v: k for k, v in self.GYM_TASKS.items()}.get(spec.id)
        if task is None:
            return None
        from cdrb_cli.envs.pointmaze.env import import_gymnasium_robotics

        return import_gymnasium_robotics().spec(f"Fetch{task}-v4")

    def details(self, spec: EnvSpec) -> dict[str, Any]:
        scene = spec.scene
        return {
            "task": scene.task,
            "walls": len(scene.walls),
            "cross": scene.cross,
            "extra_boxes": len(scene.extra_boxes),
        }

    def with_map(self, spec: EnvSpec, path, flag: str = "--scene") -> EnvSpec:
        """The model's task among the boxes a scene file puts down (:mod:`cdrb_cli.envs.fetch.scenes`)."""
        from cdrb_cli.envs.fetch.scenes import load_scene_change, with_boxes

        if str(path).lower().endswith(".txt"):
            raise BadInput(
                f"{flag} {path}: a maze map, but {spec.id} is a Fetch task",
                hint="pass a TOML scene file of [[boxes]] (docs/cli.md, `cdrb plan --help`)",
            )
        return with_boxes(spec, load_scene_change(path, flag), f"{flag} {path}")

    def scene_changed(self, spec: EnvSpec) -> bool:
        return bool(spec.scene.extra_boxes)

    def new_obstacle_crossings(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray | None:
        """Through a box put down after training, by any body (as :meth:`path_in_collision`, those boxes alone)."""
        if not spec.scene.extra_boxes:
            return None
        return paths_in_obstacles(paths, spec.scene.extra_boxes, spec.scene.task, bounded=False)

    def make_env(self, spec: EnvSpec):
        from cdrb_cli.envs.fetch.env import FetchEnv

        return FetchEnv(spec)

    def make_gym_env(self, spec: EnvSpec, seed: int):
        from cdrb_cli.envs.fetch.env import training_env

        return training_env(spec, seed)

    # -------------------------------------------------------------- protocol
    def protocol_spec(self, spec: EnvSpec, protocol: str) -> EnvSpec:
        """``official-code``: the goal pins the gripper with the block (dims 0:6, the official ``--cond-end 6``),
        and the episode is as long as the executor's budget allows (it ends when the plan runs out; Push's reset
        steps do not count toward the budget, hence the margin)."""
        if protocol != "official-code":
            return spec
        from cdrb_cli.envs.fetch.official import MAX_RESET_STEPS, official_steps

        limit = spec.horizon * official_steps(spec)
        if spec.scene.task == "push":
            limit += 4 * MAX_RESET_STEPS
        pins = list(range(6)) if has_object(spec) else spec.pinned_end_dims
        return spec.model_copy(update={"episode_limit": max(limit, spec.episode_limit), "pinned_end_dims": pins})

    def protocol_controller(self, protocol: str) -> str | None:
        return "fetch-official" if protocol == "official-code" else None

    def draw_episodes(self, spec: EnvSpec, n: int, seed: int, stream: int) -> list[Episode]:
        out = []
        for s in episode_seeds(seed, n, stream):
            start, goal = draw_task(spec.scene, np.random.default_rng([int(s), 11]))
            out.append(Episode(int(s), start, goal))
        return out

    def draw_protocol_episodes(
        self, spec: EnvSpec, n: int, seed: int, stream: int, protocol: str | None = None
    ) -> list[Episode]:
        """``detour``: the first ``n`` of the stream's draws whose shortest route in the training scene a new box
        blocks (:func:`~cdrb_cli.envs.fetch.scenes.blocks_shortest_route`); ``anywhere``: the stock draws with the
        gripper started elsewhere (:meth:`_anywhere_episodes`); the other protocols: the stock draws."""
        if protocol == ANYWHERE:
            return self._anywhere_episodes(spec, n, seed, stream)
        if protocol != DETOUR:
            return self.draw_episodes(spec, n, seed, stream)
        from cdrb_cli.envs.fetch.scenes import blocks_shortest_route

        if not spec.scene.extra_boxes:
            raise NeedsScene(
                f"protocol {DETOUR}: {spec.id} runs in the scene it was trained in, so no pair needs a detour",
                need="a TOML file of the boxes put down",
                flag="--scene",
            )
        out: list[Episode] = []
        candidates = self.draw_episodes(spec, DETOUR_SCAN * n, seed, stream)  # a prefix of the same stream
        for ep in candidates:
            start = np.asarray(spec.scene.home) if not ep.start else np.array([*ep.start, BLOCK_Z])
            if blocks_shortest_route(spec, start, np.asarray(ep.goal)):
                out.append(ep)
                if len(out) == n:
                    return out
        if not out:  # (fewer episodes would not help; an eval's first check asks for one)
            raise BadInput(
                f"protocol {DETOUR}: the boxes of {spec.scene.change} block the shortest route of none of "
                f"{len(candidates)} drawn pairs",
                hint="put the boxes where the data's routes go, across the way from a start to its goal",
            )
        raise BadInput(
            f"protocol {DETOUR}: the boxes of {spec.scene.change} block the shortest route of {len(out)} of "
            f"{len(candidates)} drawn pairs, fewer than the {n} asked for",
            hint="put the boxes where the data's routes go, or ask for fewer episodes",
        )

    def _anywhere_episodes(self, spec: EnvSpec, n: int, seed: int, stream: int) -> list[Episode]:
        """The stock draws of the stream, each with a gripper start (:func:`~cdrb_cli.envs.fetch.tasks.
        draw_gripper_start`, seeded by the episode) checked in the simulator: the grip site got within 1 cm of it
        and no part of the arm touches a wall there; a pair with no such start in :data:`ANYWHERE_TRIES` draws is
        left out for the stream's next one."""
        from cdrb_cli.envs.fetch.env import FetchEnv

        out: list[Episode] = []
        env = FetchEnv(spec)
        try:
            for ep in self.draw_episodes(spec, 4 * n, seed, stream):  # a prefix of the same stream
                rng = np.random.default_rng([ep.seed, 12])
                for _ in range(ANYWHERE_TRIES):
                    try:
                        grip = draw_gripper_start(spec.scene, rng, ep.start, ep.goal)
                    except RuntimeError:
                        raise BadInput(
                            f"protocol {ANYWHERE}: the walls and boxes of {spec.id} leave no room to start the gripper",
                            hint="use fewer or smaller boxes, or the stock protocol",
                        ) from None
                    trial = Episode(ep.seed, (*ep.start, *grip), ep.goal)
                    state, _ = env.reset(trial)
                    if np.linalg.norm(state[:3] - grip) < 0.01 and not env.robot_contacts():
                        out.append(trial)
                        break
                if len(out) == n:
                    return out
        finally:
            env.close()
        if not out:  # (fewer episodes would not help; an eval's first check asks for one)
            raise BadInput(
                f"protocol {ANYWHERE}: the arm reaches none of {4 * n} drawn pairs' gripper starts in {spec.id} "
                "without touching a wall",
                hint="use fewer or smaller boxes, or the stock protocol",
            )
        raise BadInput(
            f"protocol {ANYWHERE}: the arm reaches {len(out)} of {4 * n} drawn pairs' gripper starts in "
            f"{spec.id} without touching a wall, fewer than the {n} asked for",
            hint="ask for fewer episodes",
        )

    def goal_state(self, spec: EnvSpec, goals: np.ndarray) -> np.ndarray:
        goals = np.atleast_2d(goals)
        out = np.zeros((goals.shape[0], spec.obs_dim))
        out[:, :3] = goals  # the gripper at the goal (Reach), or touching the block there
        out[:, spec.goal_dims] = goals
        return out

    def parse_point(self, spec: EnvSpec, text: str, flag: str) -> np.ndarray:
        """``--goal x,y,z``; ``--start bx,by`` (Push, Pick & Place: the block there at rest, the gripper at home,
        the state the env resets to) or ``--start x,y,z`` (Reach: the gripper there at rest); or a full state."""
        if flag.lstrip("-") != "start" or not has_object(spec):  # the CLI's --start, the API's start
            return super().parse_point(spec, text, flag)
        values = self.numbers(text, flag)
        if len(values) == spec.obs_dim:
            return self.checked_point(spec, np.array(values), text, flag)
        if len(values) != 2:
            raise BadInput(
                f"{flag} {text!r}: expected the block's x,y (2 numbers) or a full state ({spec.obs_dim})",
                hint="e.g. --start 1.30,0.62 (the gripper starts at home)",
            )
        nominal = np.zeros(spec.obs_dim)
        nominal[:3] = spec.scene.home
        nominal[3:6] = (*values, BLOCK_Z)
        self.checked_point(spec, nominal, text, flag)
        env = self.make_env(spec)
        try:
            state, _ = env.reset(Episode(0, tuple(values), (*values, BLOCK_Z)))
        finally:
            env.close()
        return state

    def check_point(self, spec: EnvSpec, state: np.ndarray, flag: str) -> None:
        for label, value in zip(spec.state_labels, state, strict=True):
            if label.split("_")[-1][:1] in ("v", "w") and abs(value) > MAX_STEP_MOTION:
                raise BadInput(
                    f"{flag}: {label} = {value:g}: a velocity beyond {MAX_STEP_MOTION:g} per {FETCH_DT:g} s step "
                    f"({MAX_STEP_MOTION / FETCH_DT:g} m/s; a state's velocities are its motion over one step)",
                    hint="give the position only (then at rest), or velocities within the limit",
                )
        if self.in_collision(spec, state[None])[0]:
            text = ",".join(f"{v:g}" for v in state[spec.goal_dims])
            raise BadInput(
                f"{flag} {text}: the gripper or block would overlap a wall or leave the table",
                hint="choose a free point (`cdrb collect --plot` shows the walls)",
            )

    # -------------------------------------------------------------- geometry
    def in_collision(self, spec: EnvSpec, states: np.ndarray) -> np.ndarray:
        return states_in_obstacles(states, spec.scene.solid, spec.scene.task)

    def path_in_collision(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray:
        return paths_in_obstacles(paths, spec.scene.solid, spec.scene.task)

    def position_dims(self, spec: EnvSpec) -> list[int]:
        """The gripper's x, y, z and, with a block, the block's."""
        return list(range(6 if has_object(spec) else 3))

    def crossings_by_body(self, spec: EnvSpec, paths: np.ndarray) -> dict[str, np.ndarray] | None:
        """With a block: the gripper's and the block's crossings apart (their union is :meth:`path_in_collision`)."""
        if not has_object(spec):
            return None
        return paths_in_obstacles_by_body(paths, spec.scene.solid, spec.scene.task)

    def wall_crossings(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray | None:
        """Every body's walls (the fingers as wide as the plan opens them), the workspace's bounds left out: a
        gripper planned a few millimetres under the table top (Push Obstacle keeps it 6 mm above that bound all
        the way) is not a plan across the wall."""
        return paths_in_obstacles(paths, spec.scene.solid, spec.scene.task, bounded=False)

    def collisions_by_body(self, spec: EnvSpec, states: np.ndarray) -> dict[str, np.ndarray] | None:
        """With a block: the gripper's and the block's states in an obstacle apart (their union is
        :meth:`in_collision`)."""
        if not has_object(spec):
            return None
        return states_in_obstacles_by_body(states, spec.scene.solid, spec.scene.task)

    def goal_path_in_collision(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray:
        """With a block: the planned block path through a wall or off the table (a gripper that dips into the
        short wall on its way over is the controller's to avoid, and counts as "collision" if it does)."""
        if not has_object(spec):
            return self.path_in_collision(spec, paths)
        return path_crosses_boxes(paths, block_obstacles(spec.scene.solid))

    def execution_failure(self, spec: EnvSpec, states: np.ndarray, collided: bool) -> str:
        """ "grasp" when the block never moved more than :data:`MOVED` from where it started (never grasped, never
        pushed), then as any family: "collision", else "tracking"."""
        if has_object(spec):
            block = np.asarray(states)[:, 3:6]
            if np.linalg.norm(block - block[0], axis=1).max() < MOVED:
                return "grasp"
        return super().execution_failure(spec, states, collided)

    def max_step(self, spec: EnvSpec) -> float:
        return math.sqrt(3.0) * MAX_DELTA

    def route(self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray) -> tuple[str, str] | None:
        """Obstacle tasks: (sides of start and goal, "over" when the carried point rose above the walls on the way,
        else "around" + the wall end passed); no label without walls."""
        scene: FetchScene = spec.scene
        if not scene.walls:
            return None
        pts = np.asarray(states)[:, spec.goal_dims]
        names = {-1: "near", 0: "inside", 1: "far"}
        group = f"{names[side(scene, pts[0])]}->{names[side(scene, goal)]}"
        top = max(w.high[2] for w in scene.walls)
        x0, x1 = min(w.low[0] for w in scene.walls), max(w.high[0] for w in scene.walls)
        sides = np.array([side(scene, p) for p in pts])
        if np.all(sides == sides[0]):
            return group, "same side"
        change = int(np.argmax(sides != sides[0]))
        lo, hi = max(change - 3, 0), min(change + 3, len(pts))
        p = pts[lo:hi]
        if np.all((p[:, 0] > x0) & (p[:, 0] < x1)) or p[:, 2].max() > top:
            return group, "over" if p[:, 2].max() > top else "through"
        return group, "around " + ("x-" if p[:, 0].mean() < (x0 + x1) / 2 else "x+")

    # -------------------------------------------------------------- pictures
    def xy(self, spec: EnvSpec, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)[..., spec.goal_dims[:2]]

    def goal_group(self, spec: EnvSpec, goal: np.ndarray) -> int:
        return {-1: 0, 0: 1, 1: 2}[side(spec.scene, np.asarray(goal))]

    def draw_scene(self, ax, spec: EnvSpec) -> None:
        from cdrb_cli.envs.fetch.render import draw_top

        draw_top(ax, spec)

    def plot_demos(self, demos, path, n: int, seed: int):
        from cdrb_cli.envs.fetch.render import plot_demos

        return plot_demos(demos, path, n=min(n, 40), seed=seed)

    def plot_plans(self, spec: EnvSpec, plans, path, starts, goals, in_wall, title: str):
        from cdrb_cli.envs.fetch.render import plot_plans

        return plot_plans(spec, plans, path, starts, goals, in_wall, title)

    def render_frames(
        self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray, every: int, plan: np.ndarray | None = None
    ) -> list[np.ndarray]:
        from cdrb_cli.envs.fetch.render import mujoco_frames

        return mujoco_frames(spec, states, goal, every, plan=plan)


FAMILIES.register(FetchFamily())
