"""Controllers that execute a plan (the paper executes plans with a position controller, not the diffused actions).

A plan is H states, one every ``stride`` environment steps. At environment step t the plan's time is t / stride.

* ``PDController``: u = clip(kp (p* - p) + kd (v* - v)) toward the *next* planned state (index floor(t/stride)+1),
  kp = 10, kd = 1 by default (the reference measured 100% success replaying expert plans at stride 2 and 4).
* ``InverseDynamicsController``: the force that puts the ball exactly on the plan's (linearly interpolated)
  position at the next step, from PointMaze's one-step dynamics v' = v + h (g u - c v) / (m + h c),
  p' = p + h v'; clipped to the action bounds.

After the plan's last state both hold the goal.

**The plan clock.** Without ``max_lag`` the reference runs on the environment's clock (plan time t / stride).
With ``max_lag`` set, the clock pauses while the ball is more than ``max_lag`` metres from the state it is being
driven to, so a ball that lags (after a fast first step, or around a corner) catches up along the plan instead of
cutting across toward a reference that has run ahead; ``max_wait`` bounds the pause: after that many environment
steps waiting on one planned state the clock moves on anyway (a plan the ball cannot follow no longer stalls the
episode). ``look_ahead`` lets the gated clock also move *forward* to where the ball is: when one of the next
``look_ahead`` planned states is nearer the ball than the state it is driven to, the clock jumps to the nearest,
so a plan that starts behind a moving ball (a re-plan whose first states lag or jitter back) is not chased
backwards, which would stall the ball until it is back within ``max_lag`` of a state it has passed. All three are
chosen on the tuning stream (docs/design.md).

* ``WaypointController`` is the official CDRB executor: u = clip(kp (p* - p) - kd v) toward one planned state at
  a time (kp = 1, kd = 0.1), moving to the next when within ``reach`` (0.1 m) of it or after ``max_steps`` (5)
  environment steps. It ignores the plan's stride and velocities, as the official code does. The official loop
  gives the last state 20 steps and then stops, testing the final position; here the controller holds the last
  state until the episode's step limit and success is tested at every step, as for every controller.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from cdrb_cli.envs.family import Controller, ControllerConfig, ControllerEntry
from cdrb_cli.envs.registry import CONTROLLERS

#: metres; the default of ``max_lag`` (`cdrb eval --max-lag`; docs/design.md has the measurements behind it)
DEFAULT_MAX_LAG = 0.6

_MAX_LAG_HELP = (
    "the plan clock pauses while the ball is more than this many metres from the state it is driven to; "
    "null: follow the plan on the environment's clock"
)
_MAX_WAIT_HELP = "the clock moves on after this many env steps paused on one planned state (null: no timeout)"
_LOOK_AHEAD_HELP = (
    "the gated clock jumps ahead to the nearest of this many next planned states when one is nearer the ball than "
    "its target (0: never)"
)


def _check_gated_clock(config):
    if config.max_wait is not None and config.max_lag is None:
        raise ValueError("max_wait bounds the gated clock's pause: set max_lag too (or leave max_wait null)")
    if config.look_ahead and config.max_lag is None:
        raise ValueError("look_ahead moves the gated clock: set max_lag too (or leave look_ahead 0)")
    return config


class PDConfig(ControllerConfig):
    """u = clip(kp (p* - p) + kd (v* - v)) toward the next planned state."""

    name: Literal["pd"] = "pd"
    kp: float = Field(10.0, ge=0, le=1e6, description="position gain")
    kd: float = Field(1.0, ge=0, le=1e6, description="velocity gain")
    max_lag: float | None = Field(DEFAULT_MAX_LAG, gt=0, le=1e3, description=_MAX_LAG_HELP)
    max_wait: int | None = Field(None, gt=0, le=100_000, description=_MAX_WAIT_HELP)
    look_ahead: int = Field(0, ge=0, le=100_000, description=_LOOK_AHEAD_HELP)

    _gated = model_validator(mode="after")(_check_gated_clock)


class InverseDynamicsConfig(ControllerConfig):
    """The force that puts the ball exactly on the (interpolated) plan at the next step."""

    name: Literal["inverse-dynamics"] = "inverse-dynamics"
    max_lag: float | None = Field(DEFAULT_MAX_LAG, gt=0, le=1e3, description=_MAX_LAG_HELP)
    max_wait: int | None = Field(None, gt=0, le=100_000, description=_MAX_WAIT_HELP)
    look_ahead: int = Field(0, ge=0, le=100_000, description=_LOOK_AHEAD_HELP)

    _gated = model_validator(mode="after")(_check_gated_clock)


class WaypointConfig(ControllerConfig):
    """The official CDRB executor: one planned state at a time, at most ``max_steps`` env steps each."""

    name: Literal["waypoint"] = "waypoint"
    kp: float = Field(1.0, ge=0, le=1e6, description="position gain (official: 1)")
    kd: float = Field(0.1, ge=0, le=1e6, description="velocity damping (official: 0.1, i.e. d_gain = -0.1)")
    reach: float = Field(0.1, gt=0, le=1e3, description="move to the next planned state within this distance (m)")
    max_steps: int = Field(5, gt=0, le=10_000, description="env steps at most per planned state (official: 5)")


class MazeController(Controller):
    """Shared by the PointMaze controllers: the plan, its stride, and the (optionally gated) plan clock."""

    def __init__(self, stride: int, max_lag: float | None = None, max_wait: int | None = None, look_ahead: int = 0):
        if max_lag is not None and max_lag <= 0:
            raise ValueError(f"max_lag must be positive or None, got {max_lag}")
        self.stride, self.max_lag, self.max_wait, self.look_ahead = stride, max_lag, max_wait, look_ahead
        self.plan = np.zeros((1, 4))
        self.clock = self.waited = 0

    def reset(self, plan: np.ndarray) -> None:
        self.plan = np.asarray(plan, dtype=np.float64)
        self.clock = self.waited = 0

    def progress(self, t: int, stride: int) -> float:
        return (t if self.max_lag is None else self.clock) / self.stride

    def _target_index(self, step: int) -> int:
        return min(step // self.stride + 1, len(self.plan) - 1)

    def plan_time(self, obs: np.ndarray, t: int) -> int:
        """The plan time (in environment steps) to track at environment step ``t``. With ``max_lag`` this advances
        the gated clock, so call it once per environment step (``act`` does)."""
        if self.max_lag is None:
            return t
        target = self._target_index(self.clock)
        if self.look_ahead:
            ahead = self.plan[target : target + self.look_ahead + 1, :2]
            nearest = target + int(np.argmin(np.linalg.norm(ahead - obs[:2], axis=1)))
            if nearest > target:  # the ball is past its target: drive it to the state after the nearest
                self.clock, self.waited = nearest * self.stride, 0
                target = self._target_index(self.clock)
        if np.linalg.norm(self.plan[target, :2] - obs[:2]) < self.max_lag:
            self.clock += 1
        elif self.max_wait is not None and self.waited >= self.max_wait:
            self.clock = (self.clock // self.stride + 1) * self.stride  # give up on this planned state: the next
        else:
            self.waited += 1
        if self._target_index(self.clock) != target:
            self.waited = 0  # ``max_wait`` counts the steps paused on one planned state
        return self.clock


class PDController(MazeController):
    name = "pd"

    def __init__(
        self,
        stride: int,
        kp: float,
        kd: float,
        max_lag: float | None = None,
        max_wait: int | None = None,
        look_ahead: int = 0,
    ):
        super().__init__(stride, max_lag, max_wait, look_ahead)
        self.kp, self.kd = kp, kd

    def act(self, obs, t):
        target = self.plan[self._target_index(self.plan_time(obs, t))]
        u = self.kp * (target[:2] - obs[:2]) + self.kd * (target[2:4] - obs[2:4])
        return np.clip(u, -1.0, 1.0)


class InverseDynamicsController(MazeController):
    name = "inverse-dynamics"

    def __init__(
        self,
        stride: int,
        mass: float,
        damping: float,
        gear: float,
        dt: float,
        max_lag: float | None = None,
        max_wait: int | None = None,
        look_ahead: int = 0,
    ):
        super().__init__(stride, max_lag, max_wait, look_ahead)
        self.m, self.c, self.g, self.h = mass, damping, gear, dt

    def _position_at(self, step: float) -> np.ndarray:
        s = min(step / self.stride, len(self.plan) - 1)
        i = int(np.floor(s))
        j = min(i + 1, len(self.plan) - 1)
        w = s - i
        return (1 - w) * self.plan[i, :2] + w * self.plan[j, :2]

    def act(self, obs, t):
        p, v = obs[:2], obs[2:4]
        v_next = (self._position_at(self.plan_time(obs, t) + 1) - p) / self.h
        u = ((v_next - v) * (self.m + self.h * self.c) / self.h + self.c * v) / self.g
        return np.clip(u, -1.0, 1.0)


class WaypointController(Controller):
    """The official CDRB executor (see the module docstring)."""

    name = "waypoint"

    def __init__(self, config: WaypointConfig):
        self.c = config
        self.plan = np.zeros((1, 4))
        self.index = self.spent = 0

    def reset(self, plan: np.ndarray) -> None:
        self.plan = np.asarray(plan, dtype=np.float64)
        self.index, self.spent = min(1, len(self.plan) - 1), 0

    def progress(self, t: int, stride: int) -> float:
        return float(max(self.index - 1, 0))  # it has left the previous planned state and drives to ``index``

    def act(self, obs, t):
        last = len(self.plan) - 1
        if self.index < last:
            reached = np.linalg.norm(self.plan[self.index, :2] - obs[:2]) < self.c.reach
            if reached or self.spent >= self.c.max_steps:
                self.index, self.spent = self.index + 1, 0
        self.spent += 1
        u = self.c.kp * (self.plan[self.index, :2] - obs[:2]) - self.c.kd * obs[2:4]
        return np.clip(u, -1.0, 1.0)


def _pd(spec, env, config: PDConfig, stride: int) -> PDController:
    return PDController(stride, config.kp, config.kd, config.max_lag, config.max_wait, config.look_ahead)


def _inverse_dynamics(spec, env, config: InverseDynamicsConfig, stride: int) -> InverseDynamicsController:
    d = env.dynamics
    return InverseDynamicsController(
        stride, d["mass"], d["damping"], d["gear"], d["dt"], config.max_lag, config.max_wait, config.look_ahead
    )


def _waypoint(spec, env, config: WaypointConfig, stride: int) -> WaypointController:
    return WaypointController(config)


CONTROLLERS.register(ControllerEntry(PDConfig, _pd, "PD toward the next planned state"))
CONTROLLERS.register(
    ControllerEntry(
        InverseDynamicsConfig,
        _inverse_dynamics,
        "exact one-step inverse dynamics of the ball onto the interpolated plan",
    )
)
CONTROLLERS.register(
    ControllerEntry(WaypointConfig, _waypoint, "the official CDRB executor (<= 5 env steps per state)")
)
