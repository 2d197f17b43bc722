"""Controllers that execute a plan (the paper executes plans with a position controller, not the diffused actions).

A plan is H states, one every ``stride`` environment steps. At environment step t the plan's time is t / stride.

* ``PDController``: u = clip(kp (p* - p) + kd (v* - v)) toward the *next* planned state (index floor(t/stride)+1),
  kp = 10, kd = 1 by default (the reference measured 100% success replaying expert plans at stride 2 and 4).
* ``InverseDynamicsController``: the force that puts the ball exactly on the plan's (linearly interpolated)
  position at the next step, from PointMaze's one-step dynamics v' = v + h (g u - c v) / (m + h c),
  p' = p + h v'; clipped to the action bounds.

After the plan's last state both hold the goal.
"""

from __future__ import annotations

import numpy as np


class Controller:
    name = "base"

    def __init__(self, stride: int):
        self.stride = stride
        self.plan = np.zeros((1, 4))

    def reset(self, plan: np.ndarray) -> None:
        self.plan = np.asarray(plan, dtype=np.float64)

    def act(self, obs: np.ndarray, t: int) -> np.ndarray:
        raise NotImplementedError


class PDController(Controller):
    name = "pd"

    def __init__(self, stride: int, kp: float = 10.0, kd: float = 1.0):
        super().__init__(stride)
        self.kp, self.kd = kp, kd

    def act(self, obs, t):
        i = min(t // self.stride + 1, len(self.plan) - 1)
        target = self.plan[i]
        u = self.kp * (target[:2] - obs[:2]) + self.kd * (target[2:4] - obs[2:4])
        return np.clip(u, -1.0, 1.0)


class InverseDynamicsController(Controller):
    name = "inverse-dynamics"

    def __init__(self, stride: int, mass: float, damping: float, gear: float, dt: float):
        super().__init__(stride)
        self.m, self.c, self.g, self.h = mass, damping, gear, dt

    def _position_at(self, step: float) -> np.ndarray:
        s = min(step / self.stride, len(self.plan) - 1)
        i = int(np.floor(s))
        j = min(i + 1, len(self.plan) - 1)
        w = s - i
        return (1 - w) * self.plan[i, :2] + w * self.plan[j, :2]

    def act(self, obs, t):
        p, v = obs[:2], obs[2:4]
        v_next = (self._position_at(t + 1) - p) / self.h
        u = ((v_next - v) * (self.m + self.h * self.c) / self.h + self.c * v) / self.g
        return np.clip(u, -1.0, 1.0)


def make_controller(name: str, stride: int, dynamics: dict, kp: float = 10.0, kd: float = 1.0) -> Controller:
    if name == "pd":
        return PDController(stride, kp, kd)
    if name == "inverse-dynamics":
        return InverseDynamicsController(
            stride, dynamics["mass"], dynamics["damping"], dynamics["gear"], dynamics["dt"]
        )
    raise ValueError(name)
