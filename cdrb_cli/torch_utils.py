"""Torch set-up shared by the stages: device choice and CPU threads."""

from __future__ import annotations

import ctypes
import os
import sys
import time

from cdrb_cli.errors import BadInput, option

#: seconds of CPU accounting sampled to judge how many cores other work keeps busy right now
BUSY_SAMPLE_SECONDS = 0.2
#: most torch threads a run takes on its own (more rarely pays for networks of this size)
MAX_THREADS = 8


def usable_cores() -> list[int] | None:
    """The CPU ids this process may run on (its affinity mask), or None where the platform does not say."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


def _cpu_ticks(cores: list[int] | None) -> tuple[int, int] | None:
    """(idle, total) jiffies summed over ``cores`` (all CPUs when None) from /proc/stat; None where unreadable."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            return parse_cpu_ticks(fh.read(), cores)
    except (OSError, UnicodeDecodeError):
        return None


def parse_cpu_ticks(text: str, cores: list[int] | None) -> tuple[int, int] | None:
    """(idle, total) jiffies of the per-CPU lines of a /proc/stat text, summed over ``cores`` (every CPU when
    None): idle counts idle and iowait; total counts user, nice, system, idle, iowait, irq, softirq and steal (guest
    time is already inside user). None when no line of those CPUs can be read."""
    wanted = None if cores is None else {f"cpu{c}" for c in cores}
    idle = total = 0
    seen = False
    for line in text.splitlines():
        name, _, rest = line.partition(" ")
        if not name.startswith("cpu") or name == "cpu" or (wanted is not None and name not in wanted):
            continue
        try:
            v = [int(x) for x in rest.split()]
        except ValueError:
            return None
        if len(v) < 4:
            return None
        idle += v[3] + (v[4] if len(v) > 4 else 0)
        total += sum(v[:8])
        seen = True
    return (idle, total) if seen else None


def busy_cores(cores: list[int] | None = None, seconds: float = BUSY_SAMPLE_SECONDS) -> float | None:
    """How many of ``cores`` other work keeps busy now: 1 - idle share of their CPU time over ``seconds`` of
    /proc/stat, times their number (this process sleeps meanwhile, so it counts nothing). None where the platform
    has no /proc/stat (then the load average stands in)."""
    first = _cpu_ticks(cores)
    if first is None:
        return None
    time.sleep(seconds)
    second = _cpu_ticks(cores)
    if second is None or second[1] <= first[1]:
        return None
    n = len(cores) if cores is not None else max(1, os.cpu_count() or 1)
    return n * (1.0 - (second[0] - first[0]) / (second[1] - first[1]))


def cpu_threads() -> int:
    """Torch CPU threads: ``OMP_NUM_THREADS`` when set (the standard knob: give each of several runs sharing a
    machine its share), else the cores that other work leaves free right now, at least 1 and at most
    :data:`MAX_THREADS`. "Now" is a short sample of the CPU accounting, not the 1-minute load average, so an idle
    machine trains with every core whatever ran a minute ago; threads beyond the free cores would spin against the
    other work and slow the run by far more than their share (docs/cli.md)."""
    from cdrb_cli.envvars import omp_threads

    given = omp_threads()
    if given is not None:
        return min(given, 256)
    allowed = usable_cores()
    cores = max(1, min(len(allowed) if allowed else (os.cpu_count() or 1), MAX_THREADS))
    busy = busy_cores(allowed)
    if busy is None:
        try:
            busy = os.getloadavg()[0]  # runnable processes, 1-minute average (before this run adds its own)
        except (OSError, AttributeError):  # no load average on this platform
            busy = 0.0
    return max(1, min(cores, int(cores - busy + 0.5)))


#: glibc's mallopt parameters, and the largest block it lets the heap serve (its DEFAULT_MMAP_THRESHOLD_MAX on 64 bits)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, HEAP_BLOCK_MAX = -1, -3, 32 << 20


def keep_freed_memory() -> bool:
    """Let glibc's heap serve and keep blocks up to 32 MiB, instead of giving each block over ~128 KiB its own mmap
    (and the memory back at every free). A network pass at batch 64 allocates dozens of such intermediates; fresh
    pages for each cost more than the arithmetic of a cheap activation (on a 2-core AMD EPYC a batch-64 U-Net pass
    runs ~20% faster: docs/benchmarks.md §11). The process keeps up to 64 MiB of freed memory to reuse. Leaves
    the allocator alone where a user tuned it (``GLIBC_TUNABLES`` or any ``MALLOC_*`` variable), where the C library
    is not glibc, and outside Linux; returns whether it changed anything. The commands call it; the Python API
    (:mod:`cdrb_cli.api`) does not, since the process is its caller's."""
    tuned = "GLIBC_TUNABLES" in os.environ or any(k.startswith("MALLOC_") for k in os.environ)
    if not sys.platform.startswith("linux") or tuned:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, HEAP_BLOCK_MAX)) and bool(mallopt(_M_TRIM_THRESHOLD, 2 * HEAP_BLOCK_MAX))


def setup_torch(device: str = "auto", threads: int | None = None, allocator: bool = True, flag: str = "--device"):
    """Threads and device for a stage; ``allocator``: also let the heap keep freed blocks (:func:`keep_freed_memory`),
    which a command does for its own process and a library caller's process is left without; ``flag``: the option
    its errors name (the CLI's ``--device``, the API's ``device``)."""
    import torch

    if allocator:
        keep_freed_memory()
    n = threads or cpu_threads()
    torch.set_num_threads(n)
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    check_device_name(device, flag)
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise BadInput(f"{option(flag, device)}: no CUDA device is available", hint=f"use {option(flag, 'cpu')}")
    return torch.device(device)


def check_device_name(device: str, flag: str = "--device") -> None:
    """Refuse a device that is not auto, cpu or cuda[...] by its name alone (no torch import: a command whose output
    is already up to date checks it too, without starting torch)."""
    if device not in ("auto", "cpu") and not device.startswith("cuda"):
        raise BadInput(f"{option(flag, device)}: unknown device", hint="use auto, cpu or cuda")


def adam(params, lr: float):
    """Adam with its fused kernel where this torch has one for the parameters' device (one pass over all tensors
    instead of a dozen operations per tensor: ~5x faster steps on a CPU for a small U-Net); the same update up
    to float rounding. Elsewhere the multi-tensor form, which matches the per-tensor one bit for bit."""
    import torch

    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError, ValueError):  # no fused kernel for this device or dtype, or an older torch
        return torch.optim.Adam(params, lr=lr, foreach=True)
