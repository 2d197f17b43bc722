"""Typed configurations of every stage. Each artifact's manifest embeds the resolved config that produced it,
so a pipeline can tell whether a stage is up to date (same config, same parents) and skip it."""

from __future__ import annotations

import re
import typing
from typing import Annotated, ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from cdrb_cli.envs.family import ControllerConfig, ExpertConfig
from cdrb_cli.envs.registry import CONTROLLERS, EXPERTS
from cdrb_cli.method_registry import METHODS, MethodParams
from cdrb_cli.nets.config import MLPConfig, NetConfig, SieveConfig, TransformerConfig, UNetConfig  # noqa: F401
from cdrb_cli.registry import Dispatch, RegisteredName
from cdrb_cli.schema_base import Record

Features = Literal["state", "state-action"]

#: seeds are 32-bit (numpy SeedSequence words; torch.manual_seed)
MAX_SEED = 2**32 - 1
Seed = Annotated[int, Field(ge=0, le=MAX_SEED)]


# --------------------------------------------------------------------------------------------- collect
class CollectConfig(Record):
    env: str
    episodes: int = Field(gt=0, le=1_000_000)
    expert: Annotated[ExpertConfig, Dispatch(EXPERTS, key="kind", attr="config")]
    valid_fraction: float = Field(0.1, ge=0, lt=1)
    starts: str = Field(
        "protocol",
        min_length=1,
        max_length=40,
        description="where demonstrations start: the environment's protocol (mazes: its start cells), or a protocol "
        "of the family that draws other starts (mazes: anywhere = any free cell)",
    )
    seed: Seed


class CollectSummary(Record):
    episodes: int
    steps: int
    success_rate: float
    mean_length: float
    max_length: int
    states_in_walls: int = Field(description="demonstration states inside an obstacle (walls, for mazes)")
    train_episodes: int
    valid_episodes: int
    routes: dict[str, dict[str, int]] = Field(
        default_factory=dict, description="per goal cell, how many episodes left the start region by each exit"
    )
    wall_time_s: float


# --------------------------------------------------------------------------------------------- cluster
class ClusterConfig(Record):
    k: int = Field(1000, ge=0, description="number of k-means clusters; 0 keeps the full buffer")
    features: Features = "state"
    split: Literal["train", "all"] = "train"
    n_init: int = Field(1, gt=0)
    max_iter: int = Field(100, gt=0)
    graph_join: Literal["features", "position"] = Field(
        "features",
        description="how each demonstration state joins the buffer's transition graph (geodesic balls measure "
        "along it): at the nearest buffer state by every feature, or by position alone (the family's position "
        "dims: a similar velocity never joins a state to a point across a thin wall, but edges then join states "
        "of unlike velocities, so the graph's lengths grow)",
    )
    seed: Seed


class ClusterSummary(Record):
    points: int
    source_states: int
    feature_dim: int
    diameter: float
    graph_diameter: float | None = Field(
        None,
        description="the largest shortest-path distance between two buffer points along the transition graph (the "
        "largest geodesic ball that holds a whole component); None: no graph, or too large a buffer to measure",
    )
    inertia: float | None = None
    wall_time_s: float


# --------------------------------------------------------------------------------------------- train
class TrainConfig(Record):
    """Everything `cdrb train` needs besides its inputs. Every field can be set with ``--set KEY=VALUE`` or a
    ``--config`` file (``cdrb config train`` lists them); the presets (:mod:`cdrb_cli.presets`) give the values of
    the fields that have no default here."""

    method: Annotated[MethodParams, Dispatch(METHODS, key="name", attr="params")] = Field(
        description="the method and its own hyper-parameters (method.name picks it: `cdrb train --method`)"
    )
    net: NetConfig = Field(description="the network (net.kind picks it: `cdrb train --net`)")
    preset: Literal["quick", "paper"] = Field(description="the preset the defaults came from")
    features: Features = Field(description="state, or state-action (actions appended to each planned state)")
    horizon: int = Field(
        ge=1, le=100_000, description="planned states per trajectory (a policy: actions per sampled chunk)"
    )
    stride: int = Field(gt=0, le=100_000, description="environment steps per planned state")
    steps: int = Field(gt=0, le=10**12, description="gradient steps (at most 1e12: far past any run)")
    batch_size: int = Field(gt=0, le=65536, description="training windows per gradient step")
    lr: float = Field(gt=0, description="Adam learning rate")
    grad_clip: float | None = Field(1.0, gt=0, description="max gradient norm; null disables clipping")
    ema_decay: float = Field(ge=0, lt=1, description="decay of the exponential moving average of the weights")
    ema_start: int = Field(ge=0, description="the EMA copies the weights until this step")
    ema_every: int = Field(gt=0, description="update the EMA every this many steps")
    checkpoint_every: int = Field(gt=0, description="write a checkpoint into --out every this many steps")
    checkpoint_seconds: float = Field(
        60.0,
        ge=0,
        le=86400,
        description="also write a checkpoint when this many seconds passed since the last one (0: by steps only), "
        "so a slow run killed early can --resume",
    )
    split: Literal["train", "all"] = Field("train", description="episodes trained on: train, or all (no validation)")
    precision: Literal["float32", "bfloat16"] = Field(
        "float32",
        description="arithmetic of the training step's forward passes: bfloat16 runs them under torch.autocast "
        "(weights, gradients, optimizer state and evaluation stay float32); fast where the CPU has bfloat16 "
        "instructions (AVX-512 BF16, AMX) or on a GPU that supports it, slow elsewhere",
    )

    #: fields that only say when progress is saved, never what is computed: a model made with other values of
    #: them is still up to date (artifacts.existing)
    bookkeeping: ClassVar[tuple[str, ...]] = ("checkpoint_seconds",)
    start_fraction: float = Field(
        0.9, ge=0, le=1, description="share of training windows that start at an episode's first state"
    )
    seed: Seed = Field(description="network initialization and every training draw (`--seed`)")


class SettingsProfile(Record):
    """The choice of `cdrb select` a model was trained with (``cdrb train --config experiments/tuned/X.toml``):
    plan and eval start from the eval settings chosen with it, under what their own command line sets."""

    file: str = Field(description="the selection file's name")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="the selection file's sha256 when the model was trained")
    chosen: str | None = Field(None, description="what was chosen (candidate and training length)")
    eval: dict[str, typing.Any] = Field(
        default_factory=dict,
        description="the eval settings chosen with it (dotted key -> value): plan and eval's defaults for the model",
    )


class TrainState(Record):
    step: int = 0
    finished: bool = False
    wall_time_s: float = 0.0
    loss: float | None = None
    valid_loss: float | None = None
    parameters: int = 0


# --------------------------------------------------------------------------------------------- plan
#: a sampler name that some registered method offers (which ones a model accepts is its method's business)
SamplerName = Annotated[str, RegisteredName(METHODS, values=lambda entry: entry.samplers, what="sampler")]


#: the avoidance fields that repair a plan from a buffer route at a diffusion step k (each needs a method that
#: repairs, a buffer to route through and k within the model's steps)
ROUTE_STEPS = ("route_k", "fallback_route_k")


class AvoidConfig(Record):
    """How a planner keeps its plans out of obstacles, at plan time, with the model unchanged (for obstacles the
    training data never saw: `--maze-map` at plan/eval time)."""

    mask_buffer: bool = Field(
        False,
        description="buffer methods (CDRB): remove the buffer states that collide in the scene planned in before "
        "sampling, and re-draw from the remaining buffer any restored state that collides (the smallest ball that "
        "holds one)",
    )
    best_of: int = Field(
        1,
        ge=1,
        le=64,
        description="sample this many plans per start/goal pair in one batch and keep the one with the fewest "
        "steps through an obstacle, then (with avoid.first_step) one whose first step the robot can follow, then the "
        "shortest (1: one plan, as the paper)",
    )
    route_k: int | None = Field(
        None,
        ge=1,
        le=100_000,
        description="buffer methods (CDRB): start from the shortest route through the buffer's states joined by "
        "collision-free steps, degraded to step k and restored (the method's repair), instead of from random "
        "buffer states; None: sample from scratch",
    )
    fallback_route_k: int | None = Field(
        None,
        ge=1,
        le=100_000,
        description="buffer methods (CDRB): a pair whose kept plan from scratch still steps through an obstacle is "
        "sampled again, best_of times, from the shortest route through the buffer degraded to step k and restored, "
        "and the plan with the fewest steps through an obstacle (then the shortest) kept; None: no second try",
    )
    fallback_route_itself: bool = Field(
        False,
        description="with fallback_route_k: a pair whose every plan and repair still steps through an obstacle keeps "
        "the buffer route itself (buffer states joined by collision-free steps, evenly resampled to the horizon) "
        "where that route steps through none; False: the model's plans only",
    )
    first_step: bool = Field(
        False,
        description="the first planned step counts: among a pair's plans with the fewest steps through an obstacle, "
        "one that leaves the start by no more than 1.5x what the dynamics allow in one plan step is kept before a "
        "shorter one that leaps, and with fallback_route_k a pair whose kept plan leaps gets the second try too; "
        "False: crossings, then length",
    )
    retime: bool = Field(
        False,
        description="a kept plan from scratch that steps through no obstacle but leaves its start by more than 1.5x "
        "what the dynamics allow in one plan step is retimed where that brings its first step within 1.5x: the same "
        "path (its states in order, the same straight steps between them), its states respaced evenly by arc "
        "length, so the plan goes as far at a pace the robot can follow and still steps through no obstacle; "
        "False: the model's timing",
    )
    route_clearance: float = Field(
        0.0,
        ge=0,
        le=1e3,
        description="with route_k: buffer states within this distance of an obstacle (along an obstacle dimension, "
        "in its units) cost 5x per step in the route search, so routes keep that clearance where the buffer allows; "
        "0: the shortest free route",
    )
    route_buffer: str | None = Field(
        None,
        max_length=4096,
        description="the file name of the buffer artifact whose states the routes go through, for a planner that "
        "carries no buffer (Diffuser; the artifact is a parent); None: the model's own buffer",
    )
    guide_scale: float = Field(
        0.0,
        ge=0,
        le=1e6,
        description="methods with guidance (Diffuser): after every denoising step, move the plan down the gradient "
        "of its collision cost (depth inside obstacles, in raw units) by this scale; 0: no guidance",
    )

    @model_validator(mode="after")
    def _check(self) -> AvoidConfig:
        routes = any(getattr(self, field) is not None for field in ROUTE_STEPS)
        if self.route_clearance > 0 and not routes:
            raise ValueError(
                "route_clearance keeps routes clear of obstacles: set route_k or fallback_route_k too (or drop it)"
            )
        if self.fallback_route_itself and self.fallback_route_k is None:
            raise ValueError(
                "fallback_route_itself keeps the second try's route: set fallback_route_k too (or drop it)"
            )
        return self

    def check_route_buffer(self, waypoints: bool = False, plan: bool = False) -> None:
        """A route buffer without anything that routes through it is a mistake: raise one line saying so (a plan or
        eval config calls this; an eval's waypoints route through it too)."""
        if self.route_buffer is not None and not waypoints and all(getattr(self, f) is None for f in ROUTE_STEPS):
            also = "" if plan else ", or replan.waypoint_reach"
            raise ValueError(
                f"avoid.route_buffer is what routes go through: set avoid.route_k or avoid.fallback_route_k{also} "
                "too (or drop it)"
            )

    def label(self) -> str:
        """A short description, e.g. 'masked buffer, best of 8'."""
        parts = ["masked buffer"] if self.mask_buffer else []
        clear = f", clearance {self.route_clearance:g}" if self.route_clearance else ""
        parts += [f"buffer route, k {self.route_k}{clear}"] if self.route_k else []
        parts += [f"guided x{self.guide_scale:g}"] if self.guide_scale else []
        parts += [f"best of {self.best_of}"] if self.best_of > 1 else []
        parts += [f"buffer route when every plan crosses, k {self.fallback_route_k}"] if self.fallback_route_k else []
        parts += ["the route itself as a last resort"] if self.fallback_route_itself else []
        parts += ["first step within 1.5x"] if self.first_step else []
        parts += ["leaping plans retimed"] if self.retime else []
        return ", ".join(parts) or "plain"


class MaskCounts(Record):
    """What masking a buffer did: states removed before sampling, restored states re-drawn after it."""

    buffer_states: int
    removed: int = Field(description="buffer states in collision in the scene, removed before sampling")
    redrawn: int = Field(description="restored states in collision, re-drawn from the kept buffer states")
    unreachable: int = Field(description="of those, states with no kept buffer state within the largest ball")

    def warning(self) -> str | None:
        """One line when the masked buffer left restored states inside an obstacle, or kept few states."""
        kept = self.buffer_states - self.removed
        if self.unreachable:
            return (
                f"masked buffer: {self.unreachable} restored state(s) in an obstacle had no kept buffer state within "
                "the largest ball and stay there: the buffer has too few states left around the new obstacles"
            )
        if kept < 0.5 * self.buffer_states:
            return f"masked buffer: the new obstacles removed {self.removed} of {self.buffer_states} buffer states"
        return None


class PlanConfig(Record):
    sampler: SamplerName
    n: int = Field(gt=0, le=10_000, description="plans per start/goal pair")
    sample_steps: int | None = Field(None, gt=0, description="denoising steps (None: all)")
    use_ema: bool = Field(True, description="plan with the EMA weights (false: the raw weights)")
    keep_iterates: int = Field(
        0,
        ge=0,
        le=100_000,
        description="intermediate iterates kept per plan, evenly spaced over the denoising steps (`--plot` draws "
        "them); at most one per step, so a number past the steps keeps every step",
    )
    batch: int | None = Field(
        256,
        gt=0,
        le=100_000,
        description="plans sampled together; each batch draws from a random stream of its own, so another size "
        "gives other plans of the same law (None: a file from before the size was recorded)",
    )
    avoid: AvoidConfig = Field(default_factory=AvoidConfig, description="keeping plans out of obstacles")
    scene: str | None = Field(
        None, description="the name of the map file planned in instead of the model's (its content is the env)"
    )
    seed: Seed = Field(description="every sampling draw, from the buffer states or noise a plan starts from (`--seed`)")

    @model_validator(mode="after")
    def _routes(self) -> PlanConfig:
        self.avoid.check_route_buffer(plan=True)
        return self


class PlanSummary(Record):
    pairs: int
    plans: int
    in_wall_fraction: float = Field(description="planned states inside an obstacle (walls, for mazes)")
    plans_with_wall_states: int
    plans_crossing: int | None = Field(
        None, description="plans with a state in an obstacle or a straight step through one (None: not measured)"
    )
    seconds_per_batch: float
    seconds_per_plan: float
    device: str
    masked: MaskCounts | None = Field(None, description="with a masked buffer: what masking removed and re-drew")


# --------------------------------------------------------------------------------------------- eval
class ReplanConfig(Record):
    """Closed-loop execution of a planner: when to plan again during an episode, and how."""

    mode: Literal["never", "every", "deviation"] = Field(
        "never",
        description="never: one plan per episode (the paper); every: plan again every `every` env steps; deviation: "
        "plan again when the state is farther than `deviation` from where the plan has it now",
    )
    every: int | None = Field(None, gt=0, le=1_000_000, description="env steps between plans (mode every)")
    deviation: float | None = Field(
        None, gt=0, le=1e6, description="distance from the plan that triggers a new plan, in the obstacle dimensions"
    )
    min_gap: int = Field(
        1, gt=0, le=1_000_000, description="env steps at least between two plans (mode deviation: no plan storms)"
    )
    repair_k: int | None = Field(
        None,
        gt=0,
        le=100_000,
        description="repair: restore the previous plan's remainder from degradation step k (null: plan from scratch)",
    )
    repair_steps: int | None = Field(
        None, gt=0, le=100_000, description="denoising steps of a repair (null: every step from k)"
    )
    waypoint_reach: float | None = Field(
        None,
        gt=0,
        le=1e6,
        description="goals farther than one plan reaches: every plan (the first and each re-plan) aims at the point "
        "this far (in the obstacle dimensions' units, metres in the mazes) along the shortest route through the "
        "buffer's states to the goal, or at the goal once the route is that short; re-plans move the waypoint on. "
        "Routes go through the model's buffer (CDRB) or avoid.route_buffer (a planner without one), along "
        "waypoint_graph; null: every plan aims at the goal",
    )
    waypoint_graph: Literal["transitions", "free-steps"] = Field(
        "transitions",
        description="what joins the buffer states waypoint routes go through: transitions (states one "
        "demonstration visited one after the other: the data alone, no map read) or free-steps (near states "
        "joined by steps the map says are free)",
    )

    @model_validator(mode="after")
    def _check(self) -> ReplanConfig:
        if self.mode == "every" and self.every is None:
            raise ValueError("mode 'every' needs `every` (env steps between plans)")
        if self.mode == "deviation" and self.deviation is None:
            raise ValueError("mode 'deviation' needs `deviation` (a distance)")
        if self.mode != "every" and self.every is not None or self.mode != "deviation" and self.deviation is not None:
            raise ValueError(f"mode {self.mode!r} takes neither `every` nor `deviation` other than its own")
        if self.mode == "never" and (self.repair_k is not None or self.repair_steps is not None):
            raise ValueError("repair_k/repair_steps repair a plan when re-planning: set a replan mode too")
        if self.mode == "never" and self.waypoint_reach is not None:
            raise ValueError("waypoint_reach: a plan toward a waypoint needs re-plans to go on: set a replan mode too")
        if self.repair_steps is not None and self.repair_k is None:
            raise ValueError("repair_steps needs repair_k")
        if self.repair_steps is not None and self.repair_k is not None and self.repair_steps > self.repair_k:
            raise ValueError(
                f"repair_steps {self.repair_steps} > repair_k {self.repair_k}: a repair restores from step k down "
                "to 1, in at most k steps"
            )
        return self

    @classmethod
    def parse(cls, text: str) -> dict:
        """The fields of a ``--replan`` value: ``never``, ``every:N`` or ``deviation:D``."""
        mode, _, value = text.strip().partition(":")
        if mode == "never" and not value:
            return {"mode": "never"}
        # plain ASCII numbers: Python's int and float would also read 1_0, other scripts' digits, nan and inf
        value = value.strip()
        if mode == "every" and re.fullmatch(r"[0-9]{1,12}", value):
            return {"mode": "every", "every": int(value)}
        if mode == "deviation" and re.fullmatch(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]{1,3})?", value):
            return {"mode": "deviation", "deviation": float(value)}
        raise ValueError("expected never, every:N or deviation:D")

    def label(self) -> str:
        """A short human name: ``open loop``, ``every 20`` or ``deviation 0.3``, with ``, repair k=4`` and
        ``, waypoints 8 ahead``."""
        base = {"never": "open loop", "every": f"every {self.every}", "deviation": f"deviation {self.deviation}"}
        repair = "" if self.repair_k is None else f", repair k={self.repair_k}"
        ahead = "" if self.waypoint_reach is None else f", waypoints {self.waypoint_reach:g} ahead"
        return base[self.mode] + repair + ahead


#: the most evaluation seeds one eval takes (each runs up to 100,000 episodes)
MAX_EVAL_SEEDS = 1000


class EvalConfig(Record):
    episodes: int = Field(gt=0, le=100_000, description="episodes per seed")
    seeds: list[Seed] = Field(
        min_length=1, max_length=MAX_EVAL_SEEDS, description="evaluation seeds (each draws its own start/goal pairs)"
    )
    controller: Annotated[ControllerConfig, Dispatch(CONTROLLERS, key="name", attr="config")] = Field(
        description="the controller that executes each plan, and its settings"
    )
    sampler: SamplerName
    sample_steps: int | None = Field(None, gt=0, description="denoising steps (None: all)")
    use_ema: bool = Field(True, description="plan with the EMA weights (false: the raw weights)")
    extra_steps: int = Field(
        0, ge=0, le=1_000_000, description="env steps executed beyond the plan, holding its last state"
    )
    protocol: str = Field(description="the family's start/goal protocol")
    stream: Literal["test", "tune"] = Field(
        "test", description="which start/goal pairs: 'tune' (for choosing settings) or 'test' (reported tables)"
    )
    replan: ReplanConfig = Field(
        default_factory=ReplanConfig, description="planners: when to plan again during an episode, and how"
    )
    avoid: AvoidConfig = Field(default_factory=AvoidConfig, description="planners: keeping plans out of obstacles")
    scene: str | None = Field(
        None, description="the name of the map file evaluated in instead of the model's (its content is the env)"
    )
    seed: Seed = Field(description="the sampling draws of plans and policies (the pairs come from `seeds`; `--seed`)")

    @field_validator("seeds")
    @classmethod
    def _distinct(cls, seeds: list[int]) -> list[int]:
        if len(set(seeds)) != len(seeds):
            raise ValueError("repeated seeds (each seed's pairs would count twice): list each once")
        return seeds

    @model_validator(mode="after")
    def _routes(self) -> EvalConfig:
        self.avoid.check_route_buffer(waypoints=self.replan.waypoint_reach is not None)
        return self


class SeedResult(Record):
    """One training seed's eval. Rates and fractions are in [0, 1] (`cdrb report` shows them as percents)."""

    seed: Seed
    episodes: int
    success_rate: float
    weighted_success_rate: float | None = Field(
        None,
        description="episodes that succeeded with no planned state in an obstacle (the official code's weighted "
        "success: a plan with a state in a wall fails); None: a policy makes no plans, or not measured",
    )
    clean_success_rate: float | None = Field(
        None, description="episodes that succeeded with no executed collision (None: not measured)"
    )
    in_wall_fraction: float | None = Field(description="planned states in an obstacle (None: a policy makes no plans)")
    plan_crossing_rate: float | None = Field(
        None, description="plans with a state in an obstacle or a segment through one (None: not measured)"
    )
    jump_ratio: float | None = Field(
        None, description="mean over plans of the largest step between planned states / what the dynamics allow"
    )
    impossible_jump_rate: float | None = Field(None, description="plans with a step beyond what the dynamics allow")
    executed_collision_rate: float
    path_length_ratio: float | None
    plan_seconds: float
    replans: float | None = Field(None, description="re-plans per episode (closed-loop planning; None: not measured)")
    planning_seconds: float | None = Field(
        None, description="planning time of a whole episode, seconds (None: not measured)"
    )
    failures: dict[str, int] | None = Field(
        None,
        description="failed episodes per cause: plan (through an obstacle), grasp (the object never moved), collision "
        "(the executed path hit an obstacle the plan avoided), tracking (the rest); None: not classified",
    )


class EvalSummary(Record):
    """An eval's figures over its training seeds. Rates and fractions are in [0, 1] (`cdrb report` shows them as
    percents); the std fields are sample stds over seeds."""

    method: str
    model_preset: str
    model_steps: int | None = Field(
        None,
        description="training length of the model evaluated (its config.steps; a snapshot's is its step): what "
        "tells a run's final model apart from the same file before its training was extended; None in evals before "
        "schema 2.10",
    )
    model_training: str | None = Field(
        None,
        description="sha256 of the evaluated model's training settings less its seed, checkpoints and step count: "
        "models trained alike share it (seeds of one method); None in evals before schema 2.20",
    )
    variant: str | None = Field(
        None,
        description="what sets the evaluated model apart from its method as the paper defines it (e.g. 'geodesic "
        "balls'), shown in its report row; None: as the paper, and in evals before schema 2.11",
    )
    success_mean: float
    success_std: float
    weighted_success_mean: float | None = Field(None, description="SeedResult.weighted_success_rate, mean over seeds")
    weighted_success_std: float | None = None
    clean_success_mean: float | None = Field(None, description="SeedResult.clean_success_rate, mean over seeds")
    clean_success_std: float | None = None
    in_wall_mean: float | None = Field(description="None: a policy makes no plans")
    in_wall_std: float | None
    plan_crossing_mean: float | None = None
    jump_ratio_mean: float | None = None
    impossible_jump_mean: float | None = None
    executed_collision_mean: float
    path_length_ratio_mean: float | None
    plan_seconds_mean: float
    replans_mean: float | None = None
    planning_seconds_mean: float | None = None
    failures: dict[str, int] | None = Field(None, description="failed episodes per cause, summed over seeds")
    per_seed: list[SeedResult]
    wall_time_s: float
    masked: MaskCounts | None = Field(None, description="with a masked buffer: what masking removed and re-drew")


def net_classes() -> list[type[Record]]:
    """Every network config record."""
    return list(typing.get_args(typing.get_args(NetConfig)[0]))


def net_kinds() -> list[str]:
    """The ``kind`` of every network config (`cdrb train --net` choices)."""
    return [m.model_fields["kind"].default for m in net_classes()]
