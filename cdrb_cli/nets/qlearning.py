"""Diffusion-QL's networks: the noise-predicting actor, the twin critics, and their slow copies.

All are Mish MLPs (the reference's widths: 3 x 256). The actor predicts the noise of a DDPM over one action from
(noisy action, step, condition); the critics read (condition, action); ``Targets`` holds the EMA actor, the target
critics and the update counter so that one checkpoint resumes training exactly.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import nn

from cdrb_cli.nets.activations import Mish


def mlp(n_in: int, n_out: int, hidden: list[int]):
    layers, width = [], n_in
    for h in hidden:
        layers += [nn.Linear(width, h), Mish()]
        width = h
    return nn.Sequential(*layers, nn.Linear(width, n_out))


class NoiseMLP(nn.Module):
    """eps(a_t, t, cond): a 16-d sinusoidal step embedding through Linear-Mish-Linear, then a Mish MLP."""

    def __init__(self, act_dim: int, cond_dim: int, hidden: list[int]):
        super().__init__()
        self.t_mlp = nn.Sequential(nn.Linear(16, 32), Mish(), nn.Linear(32, 16))
        self.net = mlp(act_dim + 16 + cond_dim, act_dim, hidden)

    def forward(self, a, t, cond):
        half = 8
        freqs = torch.exp(-math.log(10000) * torch.arange(half, device=a.device) / (half - 1))
        emb = t.float()[:, None] * freqs[None]
        emb = torch.cat([emb.sin(), emb.cos()], dim=-1)
        return self.net(torch.cat([a, self.t_mlp(emb), cond], dim=-1))


class TwinCritic(nn.Module):
    def __init__(self, act_dim: int, cond_dim: int, hidden: list[int]):
        super().__init__()
        self.q1, self.q2 = mlp(cond_dim + act_dim, 1, hidden), mlp(cond_dim + act_dim, 1, hidden)

    def forward(self, cond, a):
        x = torch.cat([cond, a], dim=-1)
        h1, h2 = self.q1[:-1](x), self.q2[:-1](x)
        # the values themselves in float32 even under bfloat16 autocast: with the tuned rewards Q reaches ~-200,
        # where bfloat16 steps by 1.0, coarser than the temporal differences the critic learns
        with torch.autocast(device_type=x.device.type, enabled=False):
            return self.q1[-1](h1.float()), self.q2[-1](h2.float())


class Targets(nn.Module):
    """The EMA actor, the target critics and the update counter (checkpointed together)."""

    def __init__(self, actor, critic):
        super().__init__()
        self.actor, self.critic = copy.deepcopy(actor), copy.deepcopy(critic)
        for p in self.parameters():
            p.requires_grad_(False)
        self.register_buffer("updates", torch.zeros((), dtype=torch.float64))  # a count (exact to 2**53)
