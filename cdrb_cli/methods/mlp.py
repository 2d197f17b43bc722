"""The MLP baseline of the paper: (start, goal) -> the whole trajectory in one forward pass, trained with L2 to the
demonstration windows. Deterministic: n plans for the same pair are identical."""

from __future__ import annotations

import torch

from cdrb_cli.methods.base import Method, SampleResult


class MLPPlanner(Method):
    name = "mlp"
    samplers = ("direct",)

    def loss(self, batch, rng):
        start, goal = self.ends(batch, self.obs_dim)
        pred = self.pin(self.net(start, goal), start, goal)
        return torch.mean((pred - batch) ** 2)

    @torch.no_grad()
    def sample(self, net, start, goal, rng, sampler=None, steps=None, keep_iterates=0) -> SampleResult:
        return SampleResult(plans=self.pin(net(start, goal), start, goal))
