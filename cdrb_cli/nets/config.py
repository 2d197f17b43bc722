"""The networks' configs, beside the networks (and free of torch, so configs and artifacts can be read without
it): each record is the ``net`` part of a training config; ``kind`` picks the network."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator

from cdrb_cli.schema_base import Record


class UNetConfig(Record):
    """Diffuser's temporal U-Net: Conv1d over time, GroupNorm, Mish, sinusoidal step embedding."""

    kind: Literal["unet"] = "unet"
    dim: int = Field(32, gt=0, le=4096, description="base width (channels of the first level); a multiple of groups")
    dim_mults: list[Annotated[int, Field(gt=0, le=64)]] = Field(
        default_factory=lambda: [1, 4, 8], min_length=1, max_length=8, description="width multiplier of each level"
    )
    kernel_size: int = Field(5, gt=0, le=31, description="temporal convolution kernel (odd)")
    groups: int = Field(8, gt=0, description="GroupNorm groups")
    residual: bool = Field(False, description="predict x0 as the input plus a correction (x_k + f(x_k, k))")

    @field_validator("kernel_size")
    @classmethod
    def _odd(cls, k: int) -> int:
        if k % 2 == 0:
            raise ValueError("must be odd (the convolutions keep the sequence length with k // 2 padding)")
        return k


class TransformerConfig(Record):
    """A temporal transformer over planned states (the paper's architecture ablation)."""

    kind: Literal["transformer"] = "transformer"
    d_model: int = Field(128, gt=0, le=4096, description="token width; a multiple of n_heads")
    n_layers: int = Field(8, gt=0, le=64, description="encoder layers")
    n_heads: int = Field(4, gt=0, le=64, description="attention heads")
    ff_dim: int = Field(512, gt=0, le=65536, description="feed-forward width")


class MLPConfig(Record):
    """(start, goal) -> whole trajectory in one pass (the paper's MLP baseline)."""

    kind: Literal["mlp"] = "mlp"
    hidden: list[Annotated[int, Field(gt=0, le=65536)]] = Field(
        default_factory=lambda: [512, 512, 512], min_length=1, max_length=16, description="hidden layer widths"
    )


class SieveConfig(Record):
    """Diffusion BC's denoiser (Pearce et al. 2023, "MLP Sieve"): the observation+goal, the noisy actions and the
    step each embedded, then fully connected blocks that see the noisy actions and the step again at every layer
    (residuals scaled by 1/sqrt(2)). LayerNorm where the reference has BatchNorm: acting on one state with the EMA
    weights is then the very network that was trained (no batch statistics)."""

    kind: Literal["sieve"] = "sieve"
    embed_dim: int = Field(128, gt=0, le=8192, description="width of the three input embeddings")
    hidden: int = Field(512, gt=0, le=65536, description="width of the fully connected blocks")


NetConfig = Annotated[UNetConfig | TransformerConfig | MLPConfig | SieveConfig, Field(discriminator="kind")]
