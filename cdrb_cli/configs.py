"""Typed configurations of every stage. Each artifact's manifest embeds the resolved config that produced it,
so a pipeline can tell whether a stage is up to date (same config, same parents) and skip it."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from cdrb_cli.schema_base import Record

Features = Literal["state", "state-action"]


# --------------------------------------------------------------------------------------------- collect
class PlannerExpertConfig(Record):
    """The scripted maze expert: randomized shortest grid path, line-of-sight smoothing, speed-profiled pursuit."""

    kind: Literal["planner"] = "planner"
    max_speed: float = Field(6.0, gt=0, description="cruise speed, m/s (the env clips each axis at 5)")
    max_accel: float = Field(18.0, gt=0, description="braking deceleration used for the speed profile, m/s^2")
    gain: float = Field(3.0, gt=0, description="velocity-tracking gain (action per m/s of error)")
    clearance: float = Field(0.3, ge=0, description="minimum distance kept from wall boxes when smoothing, m")
    switch_radius: float = Field(0.6, gt=0, description="distance at which a waypoint counts as passed, m")
    stop_gain: float = Field(10.0, gt=0, description="speed per metre of distance on the final approach, 1/s")
    settle_radius: float = Field(0.05, gt=0, description="episode ends once this close to the goal...")
    settle_speed: float = Field(0.1, gt=0, description="...and slower than this, m/s")


class SacExpertConfig(Record):
    kind: Literal["sac"] = "sac"
    policy_path: str
    policy_sha256: str
    deterministic: bool = True


ExpertConfig = Annotated[PlannerExpertConfig | SacExpertConfig, Field(discriminator="kind")]


class CollectConfig(Record):
    env: str
    episodes: int = Field(gt=0)
    expert: ExpertConfig
    valid_fraction: float = Field(0.1, ge=0, lt=1)
    seed: int


class CollectSummary(Record):
    episodes: int
    steps: int
    success_rate: float
    mean_length: float
    max_length: int
    states_in_walls: int
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
    seed: int


class ClusterSummary(Record):
    points: int
    source_states: int
    feature_dim: int
    diameter: float
    inertia: float | None = None
    wall_time_s: float


# --------------------------------------------------------------------------------------------- nets
class UNetConfig(Record):
    """Diffuser's temporal U-Net: Conv1d over time, GroupNorm, Mish, sinusoidal step embedding."""

    kind: Literal["unet"] = "unet"
    dim: int = Field(32, gt=0)
    dim_mults: list[int] = Field(default_factory=lambda: [1, 4, 8])
    kernel_size: int = Field(5, gt=0)
    groups: int = Field(8, gt=0)
    residual: bool = Field(False, description="predict x0 as the input plus a correction (x_k + f(x_k, k))")


class TransformerConfig(Record):
    """A temporal transformer over planned states (the paper's architecture ablation)."""

    kind: Literal["transformer"] = "transformer"
    d_model: int = Field(128, gt=0)
    n_layers: int = Field(8, gt=0)
    n_heads: int = Field(4, gt=0)
    ff_dim: int = Field(512, gt=0)


class MLPConfig(Record):
    """(start, goal) -> whole trajectory in one pass (the paper's MLP baseline)."""

    kind: Literal["mlp"] = "mlp"
    hidden: list[int] = Field(default_factory=lambda: [512, 512, 512])


NetConfig = Annotated[UNetConfig | TransformerConfig | MLPConfig, Field(discriminator="kind")]


# --------------------------------------------------------------------------------------------- methods
Schedule = Literal["linear", "log", "sqrt", "sigmoid"]


class CDRBParams(Record):
    name: Literal["cdrb"] = "cdrb"
    schedule: Schedule = "linear"
    d_max: float = Field(gt=0, description="largest ball radius, in normalized feature space")
    diffusion_steps: int = Field(gt=1)
    sampler: Literal["alg1", "alg2"] = "alg1"
    loss_weight_power: float = Field(
        0.0, ge=0, description="weight each sample's loss by (eps_1 / eps_k)^p (the official code's option; 0 = off)"
    )


class DiffuserParams(Record):
    name: Literal["diffuser"] = "diffuser"
    diffusion_steps: int = Field(gt=1)
    beta_schedule: Literal["cosine", "linear"] = "cosine"
    predict: Literal["x0", "epsilon"] = "x0"
    clip_denoised: bool = True
    sampler: Literal["ddpm", "ddim"] = "ddpm"
    ddim_steps: int = Field(16, gt=0)


class MLPParams(Record):
    name: Literal["mlp"] = "mlp"


MethodParams = Annotated[CDRBParams | DiffuserParams | MLPParams, Field(discriminator="name")]


# --------------------------------------------------------------------------------------------- train
class TrainConfig(Record):
    method: MethodParams
    net: NetConfig
    preset: Literal["quick", "paper", "custom"]
    features: Features
    horizon: int = Field(gt=1, description="planned states per trajectory")
    stride: int = Field(gt=0, description="environment steps per planned state")
    steps: int = Field(gt=0)
    batch_size: int = Field(gt=0)
    lr: float = Field(gt=0)
    grad_clip: float | None = Field(1.0, description="max gradient norm; null disables clipping")
    ema_decay: float = Field(0.995, ge=0, lt=1)
    ema_start: int = Field(500, ge=0, description="the EMA copies the weights until this step")
    ema_every: int = Field(10, gt=0)
    checkpoint_every: int = Field(500, gt=0)
    split: Literal["train", "all"] = "train"
    start_fraction: float = Field(
        0.9, ge=0, le=1, description="share of training windows that start at an episode's first state"
    )
    seed: int


class TrainState(Record):
    step: int = 0
    finished: bool = False
    wall_time_s: float = 0.0
    loss: float | None = None
    valid_loss: float | None = None
    parameters: int = 0


# --------------------------------------------------------------------------------------------- plan
class PlanConfig(Record):
    sampler: str
    n: int = Field(gt=0, description="plans per start/goal pair")
    sample_steps: int | None = None
    use_ema: bool = True
    keep_iterates: int = Field(0, ge=0)
    seed: int


class PlanSummary(Record):
    pairs: int
    plans: int
    in_wall_fraction: float
    plans_with_wall_states: int
    seconds_per_batch: float
    seconds_per_plan: float
    device: str


# --------------------------------------------------------------------------------------------- eval
DEFAULT_MAX_LAG = 0.6  # m; `cdrb eval --max-lag` and quickstart (see envs/controllers.py, docs/benchmarks.md)


class EvalConfig(Record):
    episodes: int = Field(gt=0, description="episodes per seed")
    seeds: list[int]
    controller: Literal["pd", "inverse-dynamics"] = "pd"
    kp: float = 10.0
    kd: float = 1.0
    max_lag: float | None = Field(
        None, gt=0, description="plan clock pauses while the ball lags more than this (m); None: time-indexed (1.0)"
    )
    sampler: str
    sample_steps: int | None = None
    use_ema: bool = True
    extra_steps: int = Field(0, ge=0, description="env steps executed beyond the plan, holding its last state")
    protocol: str = "centre-start/corner-goal"
    seed: int


class SeedResult(Record):
    seed: int
    episodes: int
    success_rate: float
    in_wall_fraction: float
    executed_collision_rate: float
    path_length_ratio: float | None
    plan_seconds: float


class EvalSummary(Record):
    method: str
    model_preset: str
    success_mean: float
    success_std: float
    in_wall_mean: float
    in_wall_std: float
    executed_collision_mean: float
    path_length_ratio_mean: float | None
    plan_seconds_mean: float
    per_seed: list[SeedResult]
    wall_time_s: float
