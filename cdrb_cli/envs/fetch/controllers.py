"""Controllers that execute a Fetch plan.

``fetch-track``: at env step t the gripper is driven toward the plan's next grip position,
``a[:3] = clip(gain (grip*_{t+1} - grip_t) / 0.05, -1, 1)``; with a block, the fingers close when the planned
finger width drops below ``close_width`` and open otherwise (the "threshold" rule: a rule on the change of the
planned width reacts to the jitter of open fingers). With ``follow_block`` (Push), while the planned gripper is
within 8 cm of the planned block, the target moves by how far the real block is from the planned one, so the
gripper keeps pushing the block it has rather than the one it planned (on by default for Push only). After the
plan's last state the controller holds it. ``fetch-push-path`` (Push): the scripted pusher pushes the block along
the planned block path. Ceilings on the experts' own plans: docs/benchmarks.md §6.1.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.family import Controller, ControllerConfig, ControllerEntry
from cdrb_cli.envs.registry import CONTROLLERS

STEP = 0.05


class FetchTrackConfig(ControllerConfig):
    """Track the planned grip positions; gripper by a width threshold; optional block-following."""

    name: Literal["fetch-track"] = "fetch-track"
    gain: float = Field(2.0, gt=0, le=100, description="action per 5 cm of position error")
    close_width: float = Field(0.07, ge=0, le=0.2, description="close the fingers when the planned width is below")
    follow_block: bool | None = Field(
        None, description="shift the target by the block's deviation from the plan (null: on for Push tasks)"
    )


class FetchTrackController(Controller):
    name = "fetch-track"

    def __init__(self, config: FetchTrackConfig, has_object: bool, stride: int, follow: bool):
        self.c, self.has_object, self.stride, self.follow = config, has_object, stride, follow
        self.plan = np.zeros((1, 3))

    def reset(self, plan: np.ndarray) -> None:
        self.plan = np.asarray(plan, dtype=np.float64)

    def act(self, state: np.ndarray, t: int) -> np.ndarray:
        i = min(t // self.stride + 1, len(self.plan) - 1)
        target = self.plan[i, :3].copy()
        grip = state[:3]
        if self.follow:
            now = self.plan[i - 1]  # where the plan has the block at this step (the target is the next state)
            if np.linalg.norm(target - self.plan[i, 3:6]) < 0.08:
                target[:2] += state[3:5] - now[3:5]
        a = np.zeros(4)
        a[:3] = np.clip(self.c.gain * (target - grip) / STEP, -1.0, 1.0)
        if self.has_object:
            a[3] = -1.0 if self.plan[i, 9] + self.plan[i, 10] < self.c.close_width else 1.0
        return a


def _track(spec, env, config: FetchTrackConfig, stride: int) -> FetchTrackController:
    follow = spec.scene.task == "push" if config.follow_block is None else config.follow_block
    return FetchTrackController(config, spec.scene.task != "reach", stride, follow and spec.scene.task != "reach")


CONTROLLERS.register(ControllerEntry(FetchTrackConfig, _track, "track planned grip positions (Fetch)"))


class FetchPushPathConfig(ControllerConfig):
    """Push the block along the plan's block path (object-centric, as the official Push controller)."""

    name: Literal["fetch-push-path"] = "fetch-push-path"
    tolerance: float = Field(
        0.015, gt=0, le=0.2, description="the planned block path is cut to corners within this distance of it, m"
    )
    unstick: int = Field(
        0,
        ge=0,
        le=20,
        description="when a wall leaves no room behind the block for the next push, push it this many times (per "
        "plan) a few cm the free way closest to the wanted one, then go on (0: wait, as the scripted pusher)",
    )


class FetchPushPathController(Controller):
    """``fetch-push-path``: the plan's block positions become the waypoints of the scripted pusher (get behind the
    block, push, re-approach when it drifts), ending at the plan's last block position (the pinned goal). The
    plan's gripper states are not used: on Push the block's path is what a plan decides, and tracking the
    gripper alone sends a block that drifted a centimetre along another path
    (docs/notebook/2026-11-24-fetch-controllers-old-tasks.md)."""

    name = "fetch-push-path"

    def __init__(self, spec, config: FetchPushPathConfig):
        from cdrb_cli.envs.fetch.expert import FetchExpertConfig, PushExpert

        self.c = config
        self.pusher = PushExpert(spec, FetchExpertConfig())
        self.plan = np.zeros((1, 6))

    def reset(self, plan: np.ndarray) -> None:
        self.plan = np.asarray(plan, dtype=np.float64)
        self.unstuck = 0

    def _waypoints(self) -> list[np.ndarray]:
        """The planned block path's corners (Ramer-Douglas-Peucker in x-y): every leg a straight push, so the pusher
        re-approaches only where the plan turns."""
        path = self.plan[:, 3:6]
        keep = np.zeros(len(path), dtype=bool)
        keep[[0, -1]] = True
        stack = [(0, len(path) - 1)]
        while stack:
            a, b = stack.pop()
            if b - a < 2:
                continue
            ab = path[b, :2] - path[a, :2]
            rel = path[a + 1 : b, :2] - path[a, :2]
            n = float(np.linalg.norm(ab))
            d = np.abs(ab[0] * rel[:, 1] - ab[1] * rel[:, 0]) / n if n > 1e-9 else np.linalg.norm(rel, axis=1)
            i = int(np.argmax(d))
            if d[i] > self.c.tolerance:
                keep[a + 1 + i] = True
                stack += [(a, a + 1 + i), (a + 1 + i, b)]
        return [p for p in path[keep][1:]]

    def act(self, state: np.ndarray, t: int) -> np.ndarray:
        if t == 0:
            self.pusher.reset(state, self.plan[-1, 3:6], np.random.default_rng(0))
            self.pusher.targets = self._waypoints()
        action = self.pusher.act(state)
        if self.pusher.stuck and self.unstuck < self.c.unstick:
            detour = self._detour(state)
            if detour is not None:
                self.unstuck += 1
                self.pusher.targets.insert(0, detour)
                action = self.pusher.act(state)
        return action

    #: how far an unsticking push moves the block, m (more than the 2 cm at which the pusher counts a target reached)
    DETOUR = 0.04

    def _detour(self, state: np.ndarray) -> np.ndarray | None:
        """A point :data:`DETOUR` from the block in the direction (of 24) closest to the wanted push whose pre-push
        point has room for the gripper and whose way is free for the block; None when there is none."""
        p = self.pusher
        block = state[3:6]
        want = p.targets[0][:2] - block[:2]
        want = want / max(float(np.linalg.norm(want)), 1e-9)
        best, best_cos = None, -2.0
        for a in np.linspace(0.0, 2 * np.pi, 24, endpoint=False):
            d = np.array([np.cos(a), np.sin(a)])
            pre = p.pre_push(block, d)
            target = np.array([*(block[:2] + self.DETOUR * d), block[2]])
            if p.grip_router.blocked(pre, pre, end_legs=True) or p.block_router.blocked(block, target, end_legs=True):
                continue
            if float(d @ want) > best_cos:
                best, best_cos = target, float(d @ want)
        return best


def _push_path(spec, env, config: FetchPushPathConfig, stride: int) -> FetchPushPathController:
    if spec.scene.task != "push":
        from cdrb_cli.errors import BadInput

        raise BadInput(f"--controller fetch-push-path: {spec.id} is not a Push task", hint="use fetch-track")
    return FetchPushPathController(spec, config)


CONTROLLERS.register(
    ControllerEntry(
        FetchPushPathConfig,
        _push_path,
        "push the block along the planned block path (Fetch Push); its unstick detours route around the walls",
        knows_map=True,
    )
)
