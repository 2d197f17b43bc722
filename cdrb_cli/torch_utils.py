"""Torch set-up shared by the stages: device choice and CPU threads."""

from __future__ import annotations

import os

from cdrb_cli.errors import BadInput


def cpu_threads() -> int:
    """Torch CPU threads: ``OMP_NUM_THREADS`` when set (the standard knob: give each of several runs sharing a
    machine its share), else the cores the machine's load leaves free, at least 1 and at most 8. Threads beyond the
    free cores spin against the other work and slow the run by far more than their share (docs/cli.md)."""
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return min(int(env), 256)
    cores = max(1, min(os.cpu_count() or 1, 8))
    try:
        busy = os.getloadavg()[0]  # runnable processes, 1-minute average (before this run adds its own)
    except (OSError, AttributeError):  # no load average on this platform
        busy = 0.0
    return max(1, min(cores, int(cores - busy + 0.5)))


def setup_torch(device: str = "auto", threads: int | None = None):
    import torch

    n = threads or cpu_threads()
    torch.set_num_threads(n)
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise BadInput("--device cuda: no CUDA device is available", hint="use --device cpu")
    if device not in ("cpu",) and not device.startswith("cuda"):
        raise BadInput(f"--device {device!r}: unknown device", hint="use auto, cpu or cuda")
    return torch.device(device)
