"""The MLP baseline: (start, goal) -> the whole trajectory in one forward pass."""

from __future__ import annotations

import torch
from torch import nn

from cdrb_cli.nets.activations import Mish
from cdrb_cli.nets.config import MLPConfig


class TrajectoryMLP(nn.Module):
    def __init__(self, cond_dim: int, feature_dim: int, horizon: int, config: MLPConfig):
        super().__init__()
        layers, width = [], 2 * cond_dim
        for h in config.hidden:
            layers += [nn.Linear(width, h), Mish()]
            width = h
        layers.append(nn.Linear(width, horizon * feature_dim))
        self.net = nn.Sequential(*layers)
        self.horizon, self.feature_dim = horizon, feature_dim

    def forward(self, start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        out = self.net(torch.cat([start, goal], dim=-1))
        return out.view(-1, self.horizon, self.feature_dim)
