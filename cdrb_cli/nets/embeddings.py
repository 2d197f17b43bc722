from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalEmbedding(nn.Module):
    """Diffusion-step embedding: sin and cos of the raw step at geometrically spaced frequencies (base 10000)."""

    def __init__(self, dim: int):
        super().__init__()
        if dim % 2:
            raise ValueError("embedding dim must be even")
        self.dim = dim

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=k.device, dtype=torch.float32) / (half - 1))
        angles = k.float()[:, None] * freqs[None, :]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)
