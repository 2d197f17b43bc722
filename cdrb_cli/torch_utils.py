"""Torch set-up shared by the stages: device choice and CPU threads."""

from __future__ import annotations

import os

from cdrb_cli.errors import BadInput


def setup_torch(device: str = "auto", threads: int | None = None):
    import torch

    n = threads or max(1, min(os.cpu_count() or 1, 8))
    torch.set_num_threads(n)
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise BadInput("--device cuda: no CUDA device is available", hint="use --device cpu")
    if device not in ("cpu",) and not device.startswith("cuda"):
        raise BadInput(f"--device {device!r}: unknown device", hint="use auto, cpu or cuda")
    return torch.device(device)
