"""A temporal transformer over planned states (the paper's architecture ablation): each planned state is a
token (MLP embedding + positional encoding); the diffusion step is one extra token; pre-norm encoder layers;
a linear head maps tokens back to states."""

from __future__ import annotations

import math

import torch
from torch import nn

from cdrb_cli.nets.config import TransformerConfig
from cdrb_cli.nets.embeddings import SinusoidalEmbedding


def _positions(length: int, dim: int) -> torch.Tensor:
    pos = torch.arange(length, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    pe = torch.zeros(length, dim)
    pe[:, 0::2] = torch.sin(pos * freq)
    pe[:, 1::2] = torch.cos(pos * freq)
    return pe


class TemporalTransformer(nn.Module):
    def __init__(self, feature_dim: int, horizon: int, config: TransformerConfig):
        super().__init__()
        d = config.d_model
        if d % config.n_heads:
            raise ValueError("d_model must be divisible by n_heads")
        self.embed = nn.Sequential(nn.Linear(feature_dim, d), nn.GELU(), nn.Linear(d, d))
        self.step = nn.Sequential(SinusoidalEmbedding(d), nn.Linear(d, d), nn.GELU(), nn.Linear(d, d))
        self.register_buffer("pos", _positions(horizon + 1, d), persistent=False)
        layer = nn.TransformerEncoderLayer(
            d, config.n_heads, config.ff_dim, dropout=0.0, activation="gelu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, config.n_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d)
        self.head = nn.Linear(d, feature_dim)

    def forward(self, x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        H = x.shape[1]
        tokens = torch.cat([self.step(k)[:, None, :], self.embed(x)], dim=1) + self.pos[: H + 1][None]
        h = self.norm(self.encoder(tokens))
        return self.head(h[:, 1:])
