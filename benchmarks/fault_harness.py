"""Kill -9 at random points of real `cdrb` processes, then check that nothing valid was lost or corrupted and
that re-running (with --resume for training) reproduces the uninterrupted result.

Run as a script for many kills (the table in docs/reliability.md), and used by tests/test_faults.py (a few kills per
command, in CI):

    python benchmarks/fault_harness.py [--kills 20] [--seed 0] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.errors import BadInput

#: datasets whose values legitimately change between identical runs (timings)
VOLATILE = {"episodes/plan_seconds", "episodes/planning_seconds"}  # timings


def cdrb_cmd(*args) -> list[str]:
    return [sys.executable, "-m", "cdrb_cli", *map(str, args)]


def stage_commands(root: Path, train_steps: int = 150) -> dict[str, list]:
    """The commands under test (tiny settings, a checkpoint every 10 training steps), in pipeline order; each
    writes ``root/<name>.h5``."""
    settings = ["net.dim=8", "net.dim_mults=1,2", "horizon=16", "stride=10", "method.diffusion_steps=8"]
    tiny = [arg for s in settings + ["batch_size=8", "checkpoint_every=10"] for arg in ("--set", s)]
    return {
        "collect": ["collect", "maze-tight", "-n", "40", "--seed", "1"],
        "cluster": ["cluster", root / "collect.h5", "--k", "80"],
        "train": [
            "train",
            root / "collect.h5",
            "--buffer",
            root / "cluster.h5",
            "--steps",
            train_steps,
            *tiny,
            "--device",
            "cpu",
        ],
        "eval": ["eval", root / "train.h5", "--seeds", "0,1", "--episodes", "4", "--device", "cpu"],
    }


def arrays_of(path: Path) -> dict[str, np.ndarray]:
    art = artifacts.load(path)
    return {k: v for k, v in art.arrays.items() if k not in VOLATILE}


def same_arrays(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@dataclass
class FaultStats:
    kills: int = 0
    killed_before_output: int = 0
    killed_with_checkpoint: int = 0
    output_corrupt: int = 0
    rerun_mismatch: int = 0
    temp_files_left: int = 0
    delays: list[float] = field(default_factory=list)


def reference(root: Path, train_steps: int = 150) -> tuple[dict[str, dict], dict[str, float]]:
    """Run every stage once, uninterrupted; returns its arrays and wall times."""
    refs, times = {}, {}
    for name, args in stage_commands(root, train_steps).items():
        t = time.time()
        proc = subprocess.run(cdrb_cmd(*args, "--out", root / f"{name}.h5"), capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        times[name] = time.time() - t
        refs[name] = arrays_of(root / f"{name}.h5")
    return refs, times


def kill_and_rerun(
    root: Path, name: str, args: list, ref: dict, duration: float, rng: np.random.Generator, stats: FaultStats
) -> None:
    """One fault: start the command, SIGKILL it at a random moment of its expected run, check, re-run."""
    out = root / f"{name}-killed.h5"
    if out.exists():
        out.unlink()
    delay = float(rng.uniform(0.3, max(duration, 0.6)))
    stats.delays.append(delay)
    proc = subprocess.Popen(cdrb_cmd(*args, "--out", out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    stats.kills += 1
    resume = []
    if not out.exists():
        stats.killed_before_output += 1
    else:
        try:
            art = artifacts.load(out)
        except BadInput:
            stats.output_corrupt += 1
            return
        state = getattr(art.manifest, "state", None)
        if state is not None and not state.finished:
            stats.killed_with_checkpoint += 1
            resume = ["--resume"]
    leftovers = [p for p in root.iterdir() if p.name.startswith(f".{out.name}.tmp-")]
    stats.temp_files_left += len(leftovers)
    for p in leftovers:  # a crashed writer's temp file: never an artifact, safe to delete
        p.unlink()
    extra = resume if resume else (["--force"] if out.exists() else [])
    proc = subprocess.run(cdrb_cmd(*args, "--out", out, *extra), capture_output=True, text=True)
    if proc.returncode != 0 or not same_arrays(arrays_of(out), ref):
        stats.rerun_mismatch += 1


def run_faults(root: Path, kills_per_stage: int, seed: int = 0, train_steps: int = 150) -> dict[str, FaultStats]:
    root.mkdir(parents=True, exist_ok=True)
    refs, times = reference(root, train_steps)
    rng = np.random.default_rng(seed)
    stats = {}
    for name, args in stage_commands(root, train_steps).items():
        st = stats[name] = FaultStats()
        for _ in range(kills_per_stage):
            kill_and_rerun(root, name, args, refs[name], times[name], rng, st)
    return stats


def crash_before_rename(root: Path, train_steps: int = 150) -> dict[str, bool]:
    """CDRB_CRASH_BEFORE_RENAME=1 kills each writer between writing and renaming: the previous artifact (the
    reference run's) must survive byte for byte."""
    out = {}
    env = dict(os.environ, CDRB_CRASH_BEFORE_RENAME="1")
    for name, args in stage_commands(root, train_steps).items():
        target = root / f"{name}.h5"
        before = target.read_bytes()
        proc = subprocess.run(cdrb_cmd(*args, "--out", target, "--force"), env=env, capture_output=True, text=True)
        intact = proc.returncode != 0 and target.read_bytes() == before
        for p in root.iterdir():
            if p.name.startswith(f".{target.name}.tmp-"):
                p.unlink()
        out[name] = intact
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", type=Path)
    args = ap.parse_args()
    root = args.workdir or Path(tempfile.mkdtemp(prefix="cdrb-faults-"))
    t = time.time()
    stats = run_faults(root, args.kills, args.seed)
    crashed = crash_before_rename(root)
    print(
        f"| fault | stage | injected | output absent | unfinished checkpoint left | corrupt outputs | "
        f"re-run differs from uninterrupted | temp files left |  ({time.time() - t:.0f}s)"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name, s in stats.items():
        print(
            f"| SIGKILL at a random moment | {name} | {s.kills} | {s.killed_before_output} | "
            f"{s.killed_with_checkpoint} | {s.output_corrupt} | {s.rerun_mismatch} | {s.temp_files_left} |"
        )
    for name, ok in crashed.items():
        print(f"| crash between write and rename | {name} | 1 | – | – | {0 if ok else 1} | – | – |")


if __name__ == "__main__":
    main()
