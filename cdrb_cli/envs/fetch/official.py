"""The official CDRB code's Fetch executor (``fetch-official``), the controller of the ``official-code`` protocol.

Re-implemented from its description (official ``fetch_env/cdrb/json_controller_test.py``, ``evaluation_pipeline.py``):

* **Executor.** The planned states are visited in order, from the first (the pinned start). Each gets at most
  ``steps_per_state`` env steps (official: Reach 1, Reach Obstacle 13, Push 9, Push Obstacle 1, Pick & Place 6,
  Pick & Place Obstacle 2), and is left as soon as the tracked point (the grip site for Reach, the block otherwise)
  is within ``gate`` (1 cm) of its planned position, so a planned state already reached takes no step. After the
  last planned state the episode ends (:attr:`FetchOfficialController.finished`); success counts at any step. The
  plan's stride is not used.
* **Reach**: ``a = 20 (planned grip - grip)``, the mean of the last 7 such actions.
* **Pick & Place**: for 10 steps the arm moves up and sideways toward the block (the fingers idle). Then: within
  20 cm of the block it heads for the block, closing the fingers within 5 cm (opening them farther out); farther
  out it heads for the planned grip position (or the block, once it has held it). A still block (speed < 5 mm/s)
  between the fingers counts as grasped: the fingers close and the arm heads for the planned grip position.
  Actions are scaled by ``10 ln(d + 2)`` (d: the gripper's distance to the block) and averaged over the last 3.
* **Push** (object-centric, fingers idle): it *resets* behind the block (up 4 steps; over the approach point 11 cm
  behind the block, opposite the planned block position; down to 2 cm above the table; onto the block), then
  *pushes* the block toward its planned position (``a_xy = (planned block - block)_xy 8 ln(d + 2)``) while the
  gripper stays within 10 cm of it, else it resets again. Stuck (the state moved < 0.5 mm though the last action
  did not vanish): the approach point becomes the block shifted 2 cm toward the table's centre, in y then in x on
  alternate attempts. Reset steps do not count toward a planned state's budget; after more than 50 reset steps in
  a row the executor moves on to the next planned state.

A faithful reading includes the official code's quirks (its stuck flag is never cleared; later planned states get
about one reset step each once a reset has run long): the protocol measures plans as that code executed them.
"""

from __future__ import annotations

from collections import deque
from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.family import Controller, ControllerConfig, ControllerEntry
from cdrb_cli.envs.registry import CONTROLLERS

#: env steps per planned state in the official evaluation, per (task, with walls)
OFFICIAL_STEPS = {
    ("reach", False): 1,
    ("reach", True): 13,
    ("push", False): 9,
    ("push", True): 1,
    ("pick-place", False): 6,
    ("pick-place", True): 2,
}
#: the executor moves on after this many reset steps in a row (Push)
MAX_RESET_STEPS = 50
#: the table's centre, toward which a stuck pusher shifts its approach
TABLE_CENTRE = np.array([1.3, 0.744, 0.42])


class FetchOfficialConfig(ControllerConfig):
    """The official CDRB Fetch executor: one planned state at a time, a step budget each, a 1 cm gate."""

    name: Literal["fetch-official"] = "fetch-official"
    steps_per_state: int | None = Field(
        None, gt=0, le=1000, description="env steps at most per planned state (null: the official value of the task)"
    )
    gate: float = Field(0.01, gt=0, le=0.5, description="leave a planned state once the tracked point is this close, m")


def _mean(history: deque, a: np.ndarray) -> np.ndarray:
    history.append(a)
    return np.mean(history, axis=0)


class _Reach:
    def __init__(self):
        self.history: deque = deque(maxlen=7)

    def act(self, s: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, bool]:
        a = _mean(self.history, 20.0 * (target[:3] - s[:3]))
        return np.array([*a, 1.0]), False


class _Pick:
    def __init__(self):
        self.history: deque = deque(maxlen=3)
        self.gripped = False
        self.calls = 0

    def act(self, s: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, bool]:
        grip, block = s[:3], s[3:6]
        d = float(np.linalg.norm(s[6:9]))
        speed = float(np.linalg.norm(s[14:17]))
        if d < 0.2:
            a, g = block - grip, (-1.0 if d < 0.05 else 1.0)
        else:
            a, g = (block - grip) if self.gripped else (target[:3] - grip), 1.0
        if speed < 0.005 and d < 0.05:
            self.gripped = True
            a, g = target[:3] - grip, -1.0
        a = _mean(self.history, a * 10.0 * np.log(d + 2.0))
        self.calls += 1
        if self.calls <= 10:  # the opening move: up, and sideways toward the block
            return np.array([0.0, 1.0 if block[1] - grip[1] > 0 else -1.0, 1.0, 0.0]), False
        return np.array([*a, g]), False


class _Push:
    def __init__(self):
        self.resetting, self.phase, self.up_steps = True, 0, 0
        self.manual: np.ndarray | None = None
        self.attempt = 0
        self.prev_state: np.ndarray | None = None
        self.prev_action = np.zeros(4)

    def _offset(self, block: np.ndarray) -> np.ndarray:
        axis = 1 if self.attempt % 2 == 0 else 0
        out = np.zeros(3)
        out[axis] = 0.02 * np.sign(TABLE_CENTRE[axis] - block[axis])
        return out

    def act(self, s: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, bool]:
        grip, block = s[:3], s[3:6]
        d = float(np.linalg.norm(s[6:9]))
        if block[2] < 0.4:  # the block left the table: nothing to reset for
            self.resetting = False
        stuck = (
            self.prev_state is not None
            and np.linalg.norm(s - self.prev_state) < 0.0005
            and np.linalg.norm(self.prev_action) > 0.01
        )
        if stuck:
            self.manual = block + self._offset(block)
            self.attempt += 1
            self.phase = 1
        way = target[3:6] - block
        approach = block - 0.11 * way / max(float(np.linalg.norm(way)), 1e-9)
        if self.manual is not None:
            approach = self.manual
        a = np.zeros(3)
        if self.resetting:
            if self.phase == 0:
                a = np.array([0.0, 0.0, 1.0])
                self.up_steps += 1
                if self.up_steps >= 4:
                    self.phase, self.up_steps = 1, 0
            elif self.phase == 1:
                if np.linalg.norm(approach[:2] - grip[:2]) > 0.05:
                    a = np.array([*(20.0 * (approach[:2] - grip[:2])), 0.0])
                elif grip[2] > 0.42:
                    a = np.array([0.0, 0.0, -1.0])
                else:
                    self.manual, self.phase = None, 2
            elif np.linalg.norm(block[:2] - grip[:2]) > 0.05:
                a = 3.0 * (block - grip)
            else:
                self.resetting = False
        elif np.linalg.norm(block[:2] - grip[:2]) < 0.1:
            a = np.array([*((target[3:5] - block[:2]) * 8.0 * np.log(d + 2.0)), 0.0])
        elif block[2] > 0.4:
            self.resetting, self.phase, self.up_steps = True, 0, 0
        action = np.array([*a, 0.0])
        self.prev_state, self.prev_action = s.copy(), action
        return action, self.resetting


class FetchOfficialController(Controller):
    """The official executor around one of the three task controllers (see the module docstring)."""

    name = "fetch-official"

    def __init__(self, task: str, steps_per_state: int, gate: float):
        self.task, self.budget, self.gate = task, steps_per_state, gate
        self.tracked = slice(0, 3) if task == "reach" else slice(3, 6)
        self.plan = np.zeros((1, 6))
        self.reset(self.plan)

    def reset(self, plan: np.ndarray) -> None:
        self.plan = np.asarray(plan, dtype=np.float64)
        self.index, self.spent, self.resets = 0, 0, 0
        self.finished = self.bail = False
        self.sub = {"reach": _Reach, "pick-place": _Pick, "push": _Push}[self.task]()

    def progress(self, t: int, stride: int) -> float:
        return float(min(self.index, len(self.plan) - 1))

    def _advance(self, s: np.ndarray) -> None:
        while self.index < len(self.plan):
            near = np.linalg.norm(s[self.tracked] - self.plan[self.index, self.tracked]) < self.gate
            if near or self.spent >= self.budget or self.bail:
                self.index, self.spent, self.bail = self.index + 1, 0, False
                continue
            return
        self.finished = True

    def act(self, state: np.ndarray, t: int) -> np.ndarray:
        self._advance(state)
        if self.finished:
            return np.zeros(4)
        action, resetting = self.sub.act(state, self.plan[self.index])
        if resetting:  # the count runs on across planned states, so each later one gets one reset step
            self.resets += 1
            self.bail = self.resets > MAX_RESET_STEPS
        else:
            self.spent, self.resets = self.spent + 1, 0
        return np.clip(action, -1.0, 1.0)


def official_steps(spec) -> int:
    return OFFICIAL_STEPS[(spec.scene.task, bool(spec.scene.walls))]


def _official(spec, env, config: FetchOfficialConfig, stride: int) -> FetchOfficialController:
    return FetchOfficialController(spec.scene.task, config.steps_per_state or official_steps(spec), config.gate)


CONTROLLERS.register(
    ControllerEntry(
        FetchOfficialConfig,
        _official,
        "the official CDRB Fetch executor (a step budget per planned state, 1 cm gate, its pick and push rules)",
    )
)
