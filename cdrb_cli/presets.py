"""Training presets, as config values.

A preset is a set of values for the training config: the method-independent fields below (:data:`TRAIN`), the
network of each kind (:data:`NETS`), and each method's own values, which live with the method
(``MethodEntry.presets``, e.g. CDRB's T and loss weighting). Any of them can be overridden with ``--set KEY=VALUE``
or ``--config FILE``; the resolved config is recorded in the model artifact.

* ``paper``: the reference settings (temporal U-Net dim 32, mults (1, 4, 8), T = 128 diffusion steps, batch 64,
  lr 2e-4, 20k steps, EMA 0.995). Hours on 2 CPU cores; minutes on a GPU.
* ``quick``: a small U-Net (dim 16, mults (1, 2, 4), ~0.25M parameters) whose output is the input plus a
  correction (``residual``), T = 32, 3k steps, and for CDRB the loss weighted by eps_1/eps_k (the official
  code's option, p = 1): a few minutes on 2 CPU cores. Every method gets the residual output; why these two
  choices, with their measurements: docs/design.md.
"""

from __future__ import annotations

PRESETS = ("quick", "paper")
DEFAULT_PRESET = "quick"

TRAIN = {
    "quick": dict(steps=3000, batch_size=32, lr=1e-3, ema_decay=0.99, ema_start=200, ema_every=1, checkpoint_every=500),
    "paper": dict(
        steps=20000, batch_size=64, lr=2e-4, ema_decay=0.995, ema_start=2000, ema_every=10, checkpoint_every=1000
    ),
}

#: network values per preset and net kind; the net records' own defaults are the paper's settings
NETS = {
    "quick": {
        "unet": dict(dim=16, dim_mults=[1, 2, 4], residual=True),
        "transformer": dict(d_model=64, n_layers=4, n_heads=4, ff_dim=256),
        "mlp": {},
        "sieve": dict(embed_dim=64, hidden=256),
    },
    "paper": {"unet": {}, "transformer": {}, "mlp": {}, "sieve": {}},
}
