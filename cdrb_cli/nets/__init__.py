"""Networks: the temporal U-Net (Diffuser's design), a temporal transformer, and the whole-trajectory MLP.

Every trajectory network maps ``(x (B, H, F), k (B,))`` to ``(B, H, F)``; the MLP maps ``(start, goal)`` to
``(B, H, F)``."""

from __future__ import annotations

from cdrb_cli.nets.config import MLPConfig, SieveConfig, TransformerConfig, UNetConfig


def build_net(config, feature_dim: int, horizon: int, cond_dim: int = 0):
    if isinstance(config, UNetConfig):
        from cdrb_cli.nets.unet import TemporalUNet

        return TemporalUNet(feature_dim, config)
    if isinstance(config, TransformerConfig):
        from cdrb_cli.nets.transformer import TemporalTransformer

        return TemporalTransformer(feature_dim, horizon, config)
    if isinstance(config, MLPConfig):
        from cdrb_cli.nets.mlp import TrajectoryMLP

        return TrajectoryMLP(cond_dim, feature_dim, horizon, config)
    if isinstance(config, SieveConfig):
        from cdrb_cli.nets.sieve import SieveMLP

        return SieveMLP(cond_dim, feature_dim * horizon, config)
    raise TypeError(f"unknown net config {config!r}")


def horizon_multiple(config) -> int:
    """The horizon must be a multiple of this (the U-Net halves the sequence at each level but the last)."""
    if isinstance(config, UNetConfig):
        return 2 ** (len(config.dim_mults) - 1)
    return 1
