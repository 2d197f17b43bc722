"""Temporal U-Net over planned states (the design of Diffuser's maze2d model).

Convolutions run over time: the input (B, H, F) is treated as F channels of length H. Each level has two residual
blocks (Conv1d -> GroupNorm -> Mish, twice, with the step embedding added as a per-channel bias in between) and
halves the length (except the last level); the way up mirrors it with skip connections. With ``dim=32`` and
``dim_mults=(1, 4, 8)`` on 6 features this has about 3.68M parameters, like the reference model.
"""

from __future__ import annotations

import torch
from torch import nn

from cdrb_cli.nets.activations import Mish
from cdrb_cli.nets.config import UNetConfig
from cdrb_cli.nets.embeddings import SinusoidalEmbedding


class ConvNormAct(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, kernel: int, groups: int):
        super().__init__(nn.Conv1d(c_in, c_out, kernel, padding=kernel // 2), nn.GroupNorm(groups, c_out), Mish())


class ResidualTemporalBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, emb_dim: int, kernel: int, groups: int):
        super().__init__()
        self.first = ConvNormAct(c_in, c_out, kernel, groups)
        self.step_bias = nn.Sequential(Mish(), nn.Linear(emb_dim, c_out))
        self.second = ConvNormAct(c_out, c_out, kernel, groups)
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.first(x) + self.step_bias(emb)[:, :, None]
        return self.second(h) + self.skip(x)


class TemporalUNet(nn.Module):
    #: forward has no Python control flow on values or shapes: a trace of it holds for every batch size
    traceable = True

    def __init__(self, feature_dim: int, config: UNetConfig):
        super().__init__()
        dim, k, g = config.dim, config.kernel_size, config.groups
        widths = [feature_dim] + [dim * m for m in config.dim_mults]
        pairs = list(zip(widths[:-1], widths[1:]))
        for _, w in pairs:
            if w % g:
                raise ValueError(f"U-Net width {w} is not divisible by {g} GroupNorm groups")
        self.step_embedding = nn.Sequential(
            SinusoidalEmbedding(dim), nn.Linear(dim, dim * 4), Mish(), nn.Linear(dim * 4, dim)
        )
        self.down = nn.ModuleList()
        for i, (c_in, c_out) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down.append(
                nn.ModuleList(
                    [
                        ResidualTemporalBlock(c_in, c_out, dim, k, g),
                        ResidualTemporalBlock(c_out, c_out, dim, k, g),
                        nn.Identity() if last else nn.Conv1d(c_out, c_out, 3, stride=2, padding=1),
                    ]
                )
            )
        mid = widths[-1]
        self.mid = nn.ModuleList(
            [ResidualTemporalBlock(mid, mid, dim, k, g), ResidualTemporalBlock(mid, mid, dim, k, g)]
        )
        self.up = nn.ModuleList()
        for c_in, c_out in reversed(pairs[1:]):
            self.up.append(
                nn.ModuleList(
                    [
                        ResidualTemporalBlock(c_out * 2, c_in, dim, k, g),
                        ResidualTemporalBlock(c_in, c_in, dim, k, g),
                        nn.ConvTranspose1d(c_in, c_in, 4, stride=2, padding=1),
                    ]
                )
            )
        self.head = nn.Sequential(ConvNormAct(dim, dim, k, g), nn.Conv1d(dim, feature_dim, 1))
        self.residual = config.residual

    def forward(self, x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        emb = self.step_embedding(k)
        h = x.transpose(1, 2)  # (B, F, H)
        skips = []
        for block1, block2, down in self.down:
            h = block2(block1(h, emb), emb)
            skips.append(h)
            h = down(h)
        for block in self.mid:
            h = block(h, emb)
        for block1, block2, up in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            h = up(block2(block1(h, emb), emb))
        out = self.head(h).transpose(1, 2)
        return x + out if self.residual else out
