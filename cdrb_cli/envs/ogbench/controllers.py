"""The executor of plans for OGBench's point agent, whose action is a position increment: drive straight at the
next planned state not yet reached, at most one action's reach per step."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.family import Controller, ControllerConfig, ControllerEntry
from cdrb_cli.envs.ogbench.env import ACTION_SCALE
from cdrb_cli.envs.registry import CONTROLLERS


class PursuitConfig(ControllerConfig):
    """Pure pursuit of the plan's states, in order."""

    name: Literal["pursuit"] = "pursuit"
    reach: float = Field(0.5, gt=0, description="a planned state counts as reached within this distance, m")
    max_steps: int = Field(10, ge=1, description="environment steps spent on one planned state before the next")


class PursuitController(Controller):
    name = "pursuit"

    def __init__(self, config: PursuitConfig):
        self.c = config
        self.plan = np.zeros((1, 2))
        self.index = self.spent = 0

    def reset(self, plan: np.ndarray) -> None:
        self.plan = np.asarray(plan, dtype=np.float64)[:, :2]
        self.index, self.spent = min(1, len(self.plan) - 1), 0

    def progress(self, t: int, stride: int) -> float:
        return float(max(self.index - 1, 0))

    def act(self, state, t):
        xy, last = np.asarray(state, dtype=np.float64)[:2], len(self.plan) - 1
        while self.index < last and (
            np.linalg.norm(self.plan[self.index] - xy) < self.c.reach or self.spent >= self.c.max_steps
        ):
            self.index, self.spent = self.index + 1, 0
        self.spent += 1
        return np.clip((self.plan[self.index] - xy) / ACTION_SCALE, -1.0, 1.0)


def _pursuit(spec, env, config: PursuitConfig, stride: int) -> PursuitController:
    return PursuitController(config)


CONTROLLERS.register(
    ControllerEntry(PursuitConfig, _pursuit, "OGBench point: straight at the next planned state not yet reached")
)
