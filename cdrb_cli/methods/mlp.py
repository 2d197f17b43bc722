"""The MLP baseline of the paper: (start, goal) -> the whole trajectory in one forward pass, trained with L2 to the
demonstration windows. Deterministic: n plans for the same pair are identical."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import Planner, SampleResult
from cdrb_cli.methods.registry import METHODS, MethodEntry, MethodParams


class MLPParams(MethodParams):
    name: Literal["mlp"] = "mlp"
    sampler: Literal["direct"] = Field("direct", description="one forward pass")


class MLPPlanner(Planner):
    def loss(self, batch, rng):
        start, goal = self.ends(batch, self.obs_dim)
        pred = self.pin(self.net(*self.pinned_only(start, goal)).float(), start, goal)
        return torch.mean((pred - batch) ** 2)

    def _sample(self, start, goal, rng, sampler, steps, keep_iterates) -> SampleResult:
        return SampleResult(plans=self.pin(self.net(*self.pinned_only(start, goal)), start, goal))


METHODS.register(
    MethodEntry(
        params=MLPParams,
        method=MLPPlanner,
        nets=("mlp",),
        description="(start, goal) -> the whole trajectory in one pass (the paper's MLP baseline)",
    )
)
