"""Training presets.

* ``paper``: the reference settings (temporal U-Net dim 32, mults (1, 4, 8), T = 128 diffusion steps, batch 64,
  lr 2e-4, 20k steps, EMA 0.995). Hours on 2 CPU cores; minutes on a GPU.
* ``quick``: a small U-Net (dim 16, mults (1, 2, 4), ~0.25M parameters), T = 32, 3k steps: a few minutes on
  2 CPU cores, and already plans sensibly on Maze Tight (docs/benchmarks.md).

Every field can be overridden by a flag; the resolved config is recorded in the model artifact.
"""

from __future__ import annotations

from cdrb_cli.configs import MLPConfig, TransformerConfig, UNetConfig

PRESETS = ("quick", "paper")

_TRAIN = {
    "quick": dict(steps=3000, batch_size=32, lr=1e-3, ema_decay=0.99, ema_start=200, ema_every=1, checkpoint_every=500),
    "paper": dict(
        steps=20000, batch_size=64, lr=2e-4, ema_decay=0.995, ema_start=2000, ema_every=10, checkpoint_every=1000
    ),
}
_DIFFUSION_STEPS = {"quick": 32, "paper": 128}


def net_config(kind: str, preset: str):
    if kind == "unet":
        return UNetConfig(dim=16, dim_mults=[1, 2, 4]) if preset == "quick" else UNetConfig(dim=32, dim_mults=[1, 4, 8])
    if kind == "transformer":
        if preset == "quick":
            return TransformerConfig(d_model=64, n_layers=4, n_heads=4, ff_dim=256)
        return TransformerConfig(d_model=128, n_layers=8, n_heads=4, ff_dim=512)
    if kind == "mlp":
        return MLPConfig(hidden=[512, 512, 512])
    raise ValueError(kind)


def train_defaults(preset: str) -> dict:
    return dict(_TRAIN[preset])


def diffusion_steps(preset: str) -> int:
    return _DIFFUSION_STEPS[preset]
