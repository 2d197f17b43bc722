"""Mish, x * tanh(softplus(x)), written through one sigmoid.

With s = sigmoid(x), 1 + e^x = 1 / (1 - s), so tanh(softplus(x)) = (1 - (1 - s)^2) / (1 + (1 - s)^2) = p / (2 - p)
with p = s (2 - s). torch's own kernel evaluates exp, log1p and tanh, and its CPU tanh is slow: on a 2-core AMD
EPYC (AVX-512) this form runs a batch-64 U-Net pass in ~70% of the time, with outputs within 2e-6 of torch's (float64
reference, |x| <= 30; docs/benchmarks.md §11). p = s (2 - s) keeps the relative precision for negative x, where
mish(x) is tiny, and for large x p rounds to 1 and the output to x. A module without parameters: state dicts of
models trained with ``nn.Mish`` load unchanged.
"""

from __future__ import annotations

import torch
from torch import nn


def mish(x: torch.Tensor) -> torch.Tensor:
    s = torch.sigmoid(x)
    p = s * (2.0 - s)
    return x * p / (2.0 - p)


class Mish(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return mish(x)
