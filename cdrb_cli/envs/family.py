"""The environment-family interface: everything the stages need to know about one kind of environment.

An environment *family* (PointMaze; later Fetch) turns an env id into an :class:`~cdrb_cli.envs.spec.EnvSpec`,
builds the environment for a spec, draws the start/goal pairs of a protocol stream, says which state a plan is
pinned to, brings experts and controllers, tests states against its obstacles, and draws its scene. The stages
(collect, plan, eval, report) only ever talk to an :class:`EnvFamily` looked up from ``spec.family``; they never
name a family, a state index or a grid cell.

To add a family: subclass :class:`EnvFamily` in one module, register an instance in
:data:`cdrb_cli.envs.registry.FAMILIES` (one line in its ``builtins`` for a built-in family; ``FAMILIES.register``
for a plugin), register its experts and controllers in ``EXPERTS`` / ``CONTROLLERS``. See docs/design.md.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from cdrb_cli.envs.spec import EnvSpec, Scene
from cdrb_cli.errors import BadInput
from cdrb_cli.schema_base import Record
from cdrb_cli.settings import clip, comma_items

#: why a failed evaluation episode failed, in the order they are tested: a plan that went through an obstacle; the
#: object never moved (never grasped or pushed); the executed path hit an obstacle the plan avoided; the rest (the
#: controller lost the plan or ran out of time)
FAILURE_CAUSES = ("plan", "grasp", "collision", "tracking")


#: the largest magnitude a --start/--goal number may have (no state of any family comes near it)
POINT_LIMIT = 10_000.0


@dataclass(frozen=True)
class Episode:
    """One start/goal draw of a protocol stream: the reset seed, and the family's own description of where the
    episode starts and what it aims for (PointMaze: grid cells). Stages hand it back to the family's env and never
    look inside."""

    seed: int
    start: tuple
    goal: tuple


class Env(Protocol):
    """A family's environment: seeded resets from an :class:`Episode`, raw state vectors out."""

    def reset(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        """Reset to ``episode``; returns (state (obs_dim,), goal (goal_dim,))."""

    def step(self, action: np.ndarray) -> np.ndarray:
        """Apply one action; returns the next state."""

    def close(self) -> None: ...


def close_all(envs) -> None:
    """Close every env of ``envs``."""
    for env in envs:
        env.close()


class Expert(Protocol):
    """A demonstrator: ``reset`` once per episode, then ``act`` every step until ``settled`` (or the limit)."""

    def reset(self, state: np.ndarray, goal: np.ndarray, rng: np.random.Generator) -> None: ...

    def act(self, state: np.ndarray) -> np.ndarray: ...

    def settled(self, state: np.ndarray, goal: np.ndarray) -> bool: ...


class Controller(ABC):
    """Executes a plan: ``reset(plan)`` with the plan's raw states (H, D), then ``act(state, t)`` every step."""

    name: ClassVar[str] = "base"
    #: the controller has nothing left to execute: the episode ends there (an executor whose plan ran out)
    finished: bool = False

    @abstractmethod
    def reset(self, plan: np.ndarray) -> None: ...

    @abstractmethod
    def act(self, state: np.ndarray, t: int) -> np.ndarray: ...

    def progress(self, t: int, stride: int) -> float:
        """Where along the plan execution stands after ``t`` environment steps on it, in planned states (may be
        fractional): ``t / stride`` on the environment's clock (the default); a controller with a clock of its own
        says where that clock is. Closed-loop evaluation measures the deviation from the plan there, and a plan
        repair keeps the plan's remainder from there."""
        return t / stride


class ExpertConfig(Record):
    """Base of every expert's settings (stored in the demos artifact); subclasses fix ``kind``."""

    kind: str
    #: fields that come from `cdrb collect`'s own flags (e.g. a policy file and its hash): `--set` may not change them
    flag_fields: ClassVar[tuple[str, ...]] = ()

    def describe(self) -> str:
        """Where the demonstrations came from, in one line (`cdrb inspect`)."""
        return f"{self.kind} expert"


class ControllerConfig(Record):
    """Base of every controller's settings (stored in the eval artifact); subclasses fix ``name``."""

    name: str


@dataclass(frozen=True)
class ExpertEntry:
    """An expert: its settings record (whose ``kind`` Literal is the expert's name), how to build it for a spec,
    and how ``cdrb collect`` configures it (``configure(policy_file)``; experts that need no file ignore it)."""

    config: type[ExpertConfig]
    build: Callable[[EnvSpec, Any], Expert]
    configure: Callable[[Path | None], ExpertConfig]
    description: str = ""

    @property
    def name(self) -> str:
        return self.config.model_fields["kind"].default


@dataclass(frozen=True)
class ControllerEntry:
    """A controller: its settings record (whose ``name`` Literal is the controller's name) and
    ``build(spec, env, config, stride) -> Controller``."""

    config: type[ControllerConfig]
    build: Callable[[EnvSpec, Env, Any, int], Controller]
    description: str = ""
    #: it reads the scene's obstacles to steer (a detour around a wall the plan did not avoid), so what it executes
    #: is not the plan alone: a planner's row with it is "planner + map-aware controller", never a planner's own
    knows_map: bool = False

    @property
    def name(self) -> str:
        return self.config.model_fields["name"].default


class EnvFamily(ABC):
    """One kind of environment. Subclasses set the class attributes and implement the abstract methods; the other
    methods have generic defaults that work for any state vector with box obstacles."""

    #: registry key, stored in every spec as ``spec.scene.family``
    name: ClassVar[str]
    #: the family's part of the EnvSpec
    scene_type: ClassVar[type[Scene]]
    #: expert names this family accepts (EXPERTS registry); the first is the default
    experts: ClassVar[tuple[str, ...]]
    #: controller names this family accepts (CONTROLLERS registry); the first is the default
    controllers: ClassVar[tuple[str, ...]]
    #: name of the default start/goal protocol, recorded in every eval artifact
    protocol: ClassVar[str]
    #: other protocols `cdrb eval --protocol` accepts (name -> description), applied by :meth:`protocol_spec`
    extra_protocols: ClassVar[dict[str, str]] = {}
    #: extra protocols that draw other starts, which `cdrb collect --starts` may also use for demonstrations
    start_protocols: ClassVar[tuple[str, ...]] = ()
    #: extra protocols that draw their pairs from a changed scene (`--maze-map` at eval), refused without one
    scene_protocols: ClassVar[tuple[str, ...]] = ()
    #: how a --start/--goal point is written, for help and errors
    point_format: ClassVar[str] = "comma-separated numbers"
    #: whether the default expert reaches every goal it can reach given the time (a maze's path planner): then an
    #: episode it misses means the episode limit is short for the pair, which an eval says
    expert_only_times_out: ClassVar[bool] = False
    #: method name -> the avoidance settings (AvoidConfig fields) plan and eval use by default in a scene with
    #: obstacles the data never saw: each the choice of the family's tuning grid for new obstacles, restricted to
    #: what needs no extra input file (a method not named plans as it is)
    scene_avoid: ClassVar[dict[str, dict[str, Any]]] = {}
    #: method name -> the eval settings (dotted ``controller.`` / ``avoid.`` keys) an eval uses by default when it
    #: re-plans: each the choice of the family's tuning grid for re-planning (a re-plan starts where the robot is,
    #: moving, so the plan clock may need to jump ahead and a plan to be chosen among several); a controller field
    #: applies where the controller has it, and ``avoid = "plain"`` drops the ``avoid.`` ones
    replan_tuned: ClassVar[dict[str, dict[str, Any]]] = {}
    #: method name -> the ``avoid.best_of`` and ``avoid.fallback_route_k`` (the settings it may hold: the Python API
    #: applies them per call, ``api.PER_CALL``) plan and eval use by default for plans that start away from the
    #: demonstrations' starts: an eval under one of
    #: :attr:`start_protocols`, a plan with a start that :meth:`off_protocol_starts` finds outside the protocol's
    #: starts. Each the choice of the family's tuning grid for plans from anywhere (a diffusion planner that starts
    #: where the data seldom does crosses walls more often, and a known map lets it keep the best of several plans);
    #: ``avoid = "plain"`` drops it
    start_tuned: ClassVar[dict[str, dict[str, Any]]] = {}

    # -------------------------------------------------------------- environments
    @abstractmethod
    def env_ids(self) -> dict[str, str]:
        """Stock environment ids -> one-line descriptions."""

    @abstractmethod
    def make_spec(self, env_id: str) -> EnvSpec:
        """The EnvSpec of a stock id."""

    def spec_from_file(self, path: Path) -> EnvSpec | None:
        """The EnvSpec described by a file (e.g. a maze map); None when this family reads no files of this kind
        (the next family is asked); a one-line :class:`BadInput` when the file is of its kind but malformed."""
        return None

    def display_name(self, env_id: str) -> str:
        return env_id

    def details(self, spec: EnvSpec) -> dict[str, Any]:
        """Family-specific facts for ``cdrb envs --json``."""
        return {}

    @abstractmethod
    def make_env(self, spec: EnvSpec) -> Env:
        """A fresh environment for ``spec`` (close it when done)."""

    def make_gym_env(self, spec: EnvSpec, seed: int):
        """A goal-conditioned gymnasium env (dict observations, sparse reward, terminating on success) for
        training reinforcement-learning experts."""
        raise BadInput(f"{spec.id}: the {self.name} family has no gymnasium env for RL experts")

    def with_map(self, spec: EnvSpec, path: Path, flag: str = "--scene") -> EnvSpec:
        """The spec of ``spec``'s task in the scene a file describes (new obstacles at plan and eval time, with the
        model unchanged); a one-line :class:`BadInput` when the family takes no such file or the file does not fit
        the model's scene."""
        raise BadInput(f"{flag} {path}: the {self.name} environments take no new scene", hint=f"drop {flag}")

    def scene_changed(self, spec: EnvSpec) -> bool:
        """Whether ``spec`` runs in another scene than its model was trained in (:meth:`with_map`)."""
        return False

    def new_obstacle_crossings(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray | None:
        """Boolean over paths (..., T, D): a state in, or a straight step through, an obstacle the training scene did
        not have (:meth:`with_map`); None when ``spec`` runs in its training scene. Leaving the workspace does not
        count here (it is no new obstacle)."""
        return None

    def scene_change_warning(self, spec: EnvSpec) -> str | None:
        """One line when ``spec`` (from :meth:`with_map`) opens space the model's training scene had closed (the
        model has no data there); None otherwise."""
        return None

    def unconnected(self, spec: EnvSpec, starts: np.ndarray, goals: np.ndarray) -> np.ndarray | None:
        """Boolean per (start, goal) state pair: no free route joins them in ``spec``'s scene (no plan can, without
        crossing an obstacle); None where the family cannot tell."""
        return None

    # -------------------------------------------------------------- protocol
    def protocols(self) -> list[str]:
        """Every protocol name, the default first."""
        return [self.protocol, *self.extra_protocols]

    def protocol_spec(self, spec: EnvSpec, protocol: str) -> EnvSpec:
        """The spec an evaluation under ``protocol`` runs (e.g. another success radius or reset noise)."""
        return spec

    def protocol_controller(self, protocol: str) -> str | None:
        """The controller a protocol prescribes (None: the family's default)."""
        return None

    def collect_limit(self, spec: EnvSpec) -> int:
        """Environment steps a demonstration may take (`cdrb collect`; its expert may settle earlier): the
        episode limit, unless the family's data has its own episode length."""
        return spec.episode_limit

    @abstractmethod
    def draw_episodes(self, spec: EnvSpec, n: int, seed: int, stream: int) -> list[Episode]:
        """``n`` episodes of protocol ``stream`` under ``seed``: the same for every method and run."""

    def draw_protocol_episodes(
        self, spec: EnvSpec, n: int, seed: int, stream: int, protocol: str | None = None
    ) -> list[Episode]:
        """The episodes of ``protocol`` (None or one whose pairs are the default's: :meth:`draw_episodes`); a
        family whose extra protocol draws other starts (e.g. ``anywhere``) overrides this."""
        return self.draw_episodes(spec, n, seed, stream)

    def goal_state(self, spec: EnvSpec, goals: np.ndarray) -> np.ndarray:
        """The states (n, obs_dim) plans are pinned to for goals (n, goal_dim): the goal at rest."""
        goals = np.atleast_2d(goals)
        out = np.zeros((goals.shape[0], spec.obs_dim))
        out[:, spec.goal_dims] = goals
        return out

    def distance(self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Per state (..., obs_dim): distance to the goal (Euclidean in the goal dimensions)."""
        return np.linalg.norm(np.asarray(states)[..., spec.goal_dims] - goal, axis=-1)

    def success(self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Per state (..., obs_dim): is the goal reached (within ``spec.success_radius``)?"""
        return self.distance(spec, states, goal) <= spec.success_radius

    def reset_states(self, spec: EnvSpec, episodes, env: Env | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Start states (n, obs_dim) and goals (n, goal_dim) of episodes, exactly as the environment resets them
        (in ``env``, or in a fresh one)."""
        own = env is None
        env = env or self.make_env(spec)
        try:
            pairs = [env.reset(ep) for ep in episodes]
        finally:
            if own:
                env.close()
        return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])

    def numbers(self, text: str, flag: str) -> list[float]:
        """The comma-separated numbers of a --start/--goal value: plain decimals (``1_3``, ``nan``, ``inf`` and hex
        are not read as numbers, though Python's ``float`` would), each within +-10,000 (one-line error otherwise)."""
        import re

        parts = comma_items(text)  # spaces around a number, not inside it ("1 .5" is a typo)
        if parts != [""] and "" in parts:  # "0,,0" or ",0,0": a number left out, not a separator to skip
            raise BadInput(
                f"{flag} {clip(repr(text), 80)}: an empty value between commas", hint=f"write {self.point_format}"
            )
        number = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d{1,3})?")
        if not parts or len(parts) > 1000 or not all(number.fullmatch(v) for v in parts):
            raise BadInput(
                f"{flag} {clip(repr(text), 80)}: not a list of numbers", hint=f"write {self.point_format}"
            ) from None
        values = [float(v) for v in parts]
        if any(abs(v) > POINT_LIMIT for v in values):
            raise BadInput(
                f"{flag} {clip(repr(text), 80)}: a value beyond +-{POINT_LIMIT:,.0f}",
                hint=f"write {self.point_format}",
            )
        return values

    def checked_point(self, spec: EnvSpec, state: np.ndarray, text: str, flag: str) -> np.ndarray:
        """``state`` when it is finite and one the agent can be in (:meth:`check_point`); else a one-line error."""
        if not np.all(np.isfinite(state)):
            raise BadInput(f"{flag} {text!r}: values must be finite", hint=f"write {self.point_format}")
        self.check_point(spec, state, flag)
        return state

    def parse_point(self, spec: EnvSpec, text: str, flag: str) -> np.ndarray:
        """A --start/--goal value -> a state: goal coordinates (then at rest) or a full state."""
        values = self.numbers(text, flag)
        n_pos = len(spec.goal_dims)
        if len(values) == n_pos:
            state = self.goal_state(spec, np.array(values))[0]
        elif len(values) == spec.obs_dim:
            state = np.array(values)
        else:
            raise BadInput(
                f"{flag} {text!r}: expected {n_pos} or {spec.obs_dim} numbers", hint=f"write {self.point_format}"
            )
        return self.checked_point(spec, state, text, flag)

    def check_point(self, spec: EnvSpec, state: np.ndarray, flag: str) -> None:
        """Refuse a start/goal state the agent cannot be in (one-line :class:`BadInput`)."""
        if self.in_collision(spec, state[None])[0]:
            raise BadInput(f"{flag}: the state is inside an obstacle", hint="choose a free state")

    # -------------------------------------------------------------- geometry
    def in_collision(self, spec: EnvSpec, states: np.ndarray) -> np.ndarray:
        """Boolean mask over states (..., D): True where the agent overlaps an obstacle or leaves the workspace."""
        from cdrb_cli.envs.geometry import in_boxes

        return in_boxes(states, spec.obstacles)

    def path_in_collision(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray:
        """Boolean over paths (..., T, D): a state in collision, or a straight segment between two consecutive
        states that passes through an obstacle (a plan can have every state free and still jump through a wall)."""
        from cdrb_cli.envs.geometry import path_crosses_boxes

        return path_crosses_boxes(paths, spec.obstacles)

    def position_dims(self, spec: EnvSpec) -> list[int]:
        """The state dims that say where the bodies are (the buffer's transition graph joins states by them):
        the obstacle dims by default."""
        return list(spec.obstacles.dims)

    def crossings_by_body(self, spec: EnvSpec, paths: np.ndarray) -> dict[str, np.ndarray] | None:
        """For a family whose plans move more than one body (Fetch: the gripper and the block): body name -> boolean
        over paths (..., T, D), a state of that body in, or a step of it through, an obstacle (their union is
        :meth:`path_in_collision`); None for one body."""
        return None

    def wall_crossings(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray | None:
        """Boolean over paths (..., T, D): a state in, or a step through, a wall, the workspace's bounds not
        counted (:meth:`path_in_collision` counts both: a Fetch gripper planned under the table top is out of
        reach, not across a wall); None where the two are the same test."""
        return None

    def collisions_by_body(self, spec: EnvSpec, states: np.ndarray) -> dict[str, np.ndarray] | None:
        """As :meth:`crossings_by_body` for states (..., D): body name -> boolean, that body in an obstacle (their
        union is :meth:`in_collision`); None for one body."""
        return None

    def crossing_counts(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray:
        """Per path (..., T, D): how many of its T - 1 straight steps touch an obstacle (a step counts when either
        end is in collision or the segment between them passes through one): :meth:`path_in_collision` of each
        two-state segment, so it holds for every family."""
        paths = np.asarray(paths)
        segments = np.stack([paths[..., :-1, :], paths[..., 1:, :]], axis=-2)  # (..., T-1, 2, D)
        return np.asarray(self.path_in_collision(spec, segments), dtype=bool).sum(axis=-1)

    def collision_cost(self, spec: EnvSpec):
        """A differentiable cost of raw states (torch, (..., D)) that is 0 outside every obstacle and grows with the
        depth inside one (:func:`~cdrb_cli.envs.geometry.box_penetration` over ``spec.obstacles`` grown by the
        agent's radius), for collision-guided sampling; None when the family has none."""
        from cdrb_cli.envs.geometry import box_arrays, box_penetration

        ob = spec.obstacles
        centers, halves = box_arrays(ob)
        dims = list(ob.dims)
        return lambda states: box_penetration(states[..., dims], centers, halves, ob.inflate)

    def goal_path_in_collision(self, spec: EnvSpec, paths: np.ndarray) -> np.ndarray:
        """Boolean over paths (..., T, D): the planned path of what the task brings to the goal crosses an obstacle
        (a failed episode's cause "plan"). Here the agent's whole path (:meth:`path_in_collision`); Fetch with a
        block tests the block's path, which a plan exists to decide."""
        return self.path_in_collision(spec, paths)

    def execution_failure(self, spec: EnvSpec, states: np.ndarray, collided: bool) -> str:
        """Why an executed episode (states (T, D)) whose plans were free did not reach its goal: one of
        :data:`FAILURE_CAUSES` but "plan". Here "collision" when the path touched an obstacle, else "tracking" (the
        controller did not follow the plan to the goal in time); a family with objects adds "grasp"."""
        return "collision" if collided else "tracking"

    def off_protocol_starts(self, spec: EnvSpec, starts: np.ndarray) -> np.ndarray:
        """Boolean per raw start state (n, obs_dim): outside the region the default protocol (and so the stock
        demonstrations) start from. Here none: a family without the notion plans every start alike."""
        return np.zeros(len(np.asarray(starts)), dtype=bool)

    def max_step(self, spec: EnvSpec) -> float | None:
        """The largest distance (over the obstacle dimensions) the dynamics can move the agent in one environment
        step; None when the family has no such bound. A plan step of stride s may move s times this."""
        return None

    def plan_step_limit(self, spec: EnvSpec, stride: int) -> float | None:
        """What the dynamics allow in one plan step of ``stride`` env steps (over the obstacle dimensions): the
        tolerance first-step and jump checks compare against; None when the family has no bound."""
        max_step = self.max_step(spec)
        return None if max_step is None else float(max_step * stride)

    def path_length(self, spec: EnvSpec, states: np.ndarray) -> float:
        """Length of a path of states (T, D), measured in the goal dimensions."""
        return float(np.linalg.norm(np.diff(np.asarray(states)[:, spec.goal_dims], axis=0), axis=1).sum())

    def route(self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray) -> tuple[str, str] | None:
        """(goal group, route label) of a demonstration, counted by ``cdrb collect`` to show multimodality."""
        return None

    # -------------------------------------------------------------- pictures
    def xy(self, spec: EnvSpec, states: np.ndarray) -> np.ndarray:
        """The 2-D picture coordinates (..., 2) of states (..., D)."""
        return np.asarray(states)[..., spec.goal_dims[:2]]

    def speed(self, spec: EnvSpec, states: np.ndarray) -> np.ndarray | None:
        """A speed per state (pictures colour buffers by it), or None."""
        return None

    def goal_group(self, spec: EnvSpec, goal: np.ndarray) -> int:
        """Which goal region ``goal`` belongs to (pictures colour demonstrations by it)."""
        return 0

    def draw_scene(self, ax, spec: EnvSpec) -> None:
        """Draw the obstacles (and anything else fixed) on a matplotlib axes, in :meth:`xy` coordinates."""
        from matplotlib.patches import Rectangle

        from cdrb_cli.envs.geometry import box_arrays

        ob = spec.obstacles
        centers, halves = box_arrays(ob)
        for c, h in zip(centers[:, :2], halves[:, :2]):
            ax.add_patch(Rectangle(c - h, 2 * h[0], 2 * h[1], color="#555555", lw=0, zorder=1))
        ax.set_xlim(ob.low[0], ob.high[0])
        ax.set_ylim(ob.low[1], ob.high[1])
        ax.set_aspect("equal")

    def plot_demos(self, demos, path: Path, n: int, seed: int) -> Path | None:
        """The family's own picture of demonstrations (e.g. several views); None: the generic one."""
        return None

    def plot_plans(self, spec: EnvSpec, plans, path: Path, starts, goals, in_wall, title: str) -> Path | None:
        """The family's own picture of plans (e.g. several views); None: the generic top view."""
        return None

    def render_frames(
        self, spec: EnvSpec, states: np.ndarray, goal: np.ndarray, every: int, plan: np.ndarray | None = None
    ) -> list[np.ndarray]:
        """Simulator frames of the agent following ``states``, with ``plan`` (planned states) drawn into the scene
        when given (raise when the simulator cannot render here; the caller then draws the rollout with
        matplotlib)."""
        raise NotImplementedError(f"the {self.name} family renders no simulator frames")

    # -------------------------------------------------------------- interop (dataset files, Minari datasets)
    def dataset_env(self, path: Path) -> str | None:
        """The env id an outside dataset file of this family's format names (`cdrb import npz`), or None."""
        return None

    def read_dataset(self, spec: EnvSpec, path: Path) -> tuple[list, list, list, list, ExpertConfig] | None:
        """The episodes of an outside dataset file for ``spec`` (`cdrb import npz`): per episode the states, the
        actions with a zero last row, the goals per state and success, then the file's provenance record; None
        when the family reads no such files. A malformed file is a one-line :class:`BadInput`."""
        return None

    def from_gym(self, gym_id: str, kwargs: dict, name: str) -> EnvSpec | None:
        """The cdrb spec of the gymnasium environment ``gym_id`` made with ``kwargs`` (a Minari dataset's
        env_spec; ``name`` names a new layout), or None when it is not one of this family's."""
        return None

    def to_gym(self, spec: EnvSpec):
        """The gymnasium ``EnvSpec`` equivalent to ``spec`` (a Minari dataset's env_spec), or None when no
        registered gymnasium environment is (e.g. the Fetch tasks with walls)."""
        return None
