"""The floor every planner must beat: the straight line from start to goal, with nothing learned.

Each planned state interpolates the start and goal linearly (every feature, in normalized space; the action part
of state-action features is the middle of its range), at the horizon and stride of the training config, so the plan
is executed by the same controller as any other method's. A Table-1 row compares a method with the others only
where it beats this line on the same pairs and controller: a pair the straight line solves needs no planning.

It has no network and no weights. Training only measures the line's L2 error to the demonstration windows (the
loss curve a learned planner starts above), so `cdrb train --method straight` writes its model in seconds.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import NonFiniteLoss, Planner, SampleResult
from cdrb_cli.methods.registry import METHODS, MethodEntry, MethodParams


class StraightParams(MethodParams):
    name: Literal["straight"] = "straight"
    sampler: Literal["line"] = Field("line", description="the straight line from start to goal")


class StraightLine(Planner):
    def build(self, buffer_points) -> None:
        """No network: nothing is learned."""

    def modules(self) -> dict:
        return {}

    def make_optimizers(self) -> dict:
        return {}

    def line(self, start, goal):
        """(P, H, F): the start and goal states joined by a straight line (actions, if any, at 0)."""
        w = torch.linspace(0.0, 1.0, self.horizon, device=start.device, dtype=start.dtype)[None, :, None]
        states = start[:, None, :] * (1 - w) + goal[:, None, :] * w
        out = torch.zeros(start.shape[0], self.horizon, self.feature_dim, device=start.device, dtype=start.dtype)
        out[..., : self.obs_dim] = states
        return self.pin(out, start, goal)

    def loss(self, batch, rng):
        start, goal = self.ends(batch, self.obs_dim)
        return torch.mean((self.line(start, goal) - batch) ** 2)

    def update(self, batch, rng, optimizers) -> float:
        with torch.no_grad():
            loss = self.loss(batch, rng)
        if not torch.isfinite(loss):
            raise NonFiniteLoss(float(loss))
        return float(loss)

    def _sample(self, start, goal, rng, sampler, steps, keep_iterates) -> SampleResult:
        return SampleResult(plans=self.line(start, goal))


METHODS.register(
    MethodEntry(
        params=StraightParams,
        method=StraightLine,
        nets=("mlp",),  # recorded in its config; no network is built
        train_defaults={preset: {"steps": 50, "checkpoint_every": 50} for preset in ("quick", "paper")},
        description="the straight line from start to goal, nothing learned: the floor every planner must beat",
    )
)
