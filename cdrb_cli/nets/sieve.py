"""Diffusion BC's denoiser, the "MLP Sieve" of Pearce et al. (2023), rebuilt from its description.

Inputs: the conditioning vector (observation and goal), the noisy action chunk y (flattened) and the diffusion step
as the scalar t/T. Each is embedded (two linear layers for the condition and y, a sine layer for t), the three
embeddings are concatenated into a first block, and every later block sees the raw noisy actions and t again next
to the hidden state (so the noise level and the actions being denoised are never washed out); blocks after the
first are residual, scaled by 1/sqrt(2). Output: the predicted noise, the shape of y.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from cdrb_cli.nets.config import SieveConfig


class _Block(nn.Module):
    def __init__(self, width_in: int, width_out: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(width_in, width_out), nn.LayerNorm(width_out), nn.GELU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class SieveMLP(nn.Module):
    def __init__(self, cond_dim: int, y_dim: int, config: SieveConfig):
        super().__init__()
        e, h = config.embed_dim, config.hidden
        self.cond = nn.Sequential(nn.Linear(cond_dim, e), nn.LeakyReLU(), nn.Linear(e, e))
        self.y = nn.Sequential(nn.Linear(y_dim, e), nn.LeakyReLU(), nn.Linear(e, e))
        self.t_in = nn.Linear(1, e, bias=False)
        self.t_out = nn.Linear(e, e)
        self.fc1 = _Block(3 * e, h)
        self.fc2 = _Block(h + y_dim + 1, h)
        self.fc3 = _Block(h + y_dim + 1, h)
        self.out = nn.Linear(h + y_dim + 1, y_dim)

    def forward(self, y: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """``y`` (B, y_dim) noisy actions, ``t`` (B, 1) the step as t/T in (0, 1], ``cond`` (B, cond_dim)."""
        te = self.t_out(torch.sin(self.t_in(t)))
        h = self.fc1(torch.cat([self.cond(cond), self.y(y), te], dim=-1))
        h = (self.fc2(torch.cat([h, y, t], dim=-1)) + h) / math.sqrt(2)
        h = (self.fc3(torch.cat([h, y, t], dim=-1)) + h) / math.sqrt(2)
        return self.out(torch.cat([h, y, t], dim=-1))
