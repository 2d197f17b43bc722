"""Kill -9 at random points of real `cdrb` processes, then check that nothing valid was lost or corrupted and
that re-running (with --resume for training) reproduces the uninterrupted result.

Run as a script for many kills (the table in docs/reliability.md), and used by tests/test_faults.py (a few kills per
command, in CI):

    python benchmarks/fault_harness.py [--kills 20] [--seed 0] [--workdir DIR] [--warm]

Each command runs as a fresh interpreter, or with ``--warm`` as a fork of the grid's warm server (its imports done:
the same `cdrb_cli.cli.main`, the same writes, and every kill lands in the command's own work instead of in its
3-4 s of imports; the tests use it).
"""

from __future__ import annotations

import argparse
import contextlib
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


class Launcher:
    """Starts `cdrb` commands: fresh interpreters, or (``warm``) forks of one warm server
    (:class:`cdrb_cli.orchestration.grid.warm.WarmServer`), whose task processes die by SIGKILL as any other."""

    def __init__(self, root: Path, warm: bool = False):
        self.root, self.server, self.logs = root, None, []
        if warm:
            from cdrb_cli.orchestration.grid.warm import WarmServer

            self.server = WarmServer()

    def _fork(self, args: list, env: dict | None):
        """A forked command, its stderr in a fresh file kept until :meth:`close` (the child opens it only after
        the server has answered)."""
        fd, log = tempfile.mkstemp(prefix="task-", suffix=".err", dir=self.root)
        os.close(fd)
        self.logs.append(log)
        return self.server.start([str(a) for a in args], dict(env or os.environ), Path(log)), Path(log)

    def start(self, args: list, env: dict | None = None):
        """The command's process (``kill``, ``wait``), its output discarded."""
        if self.server is None:
            return subprocess.Popen(cdrb_cmd(*args), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return self._fork(args, env)[0]

    def run(self, args: list, env: dict | None = None) -> tuple[int, str]:
        """Run the command to its end: (exit code, stderr)."""
        if self.server is None:
            proc = subprocess.run(cdrb_cmd(*args), env=env, capture_output=True, text=True)
            return proc.returncode, proc.stderr
        task, log = self._fork(args, env)
        return task.wait(), log.read_text(errors="replace")

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
        for log in self.logs:
            with contextlib.suppress(OSError):
                os.unlink(log)


@contextlib.contextmanager
def launcher(root: Path, warm: bool = False):
    launch = Launcher(root, warm)
    try:
        yield launch
    finally:
        launch.close()


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
    failed_before_kill: int = 0
    delays: list[float] = field(default_factory=list)


def reference(root: Path, launch: Launcher, train_steps: int = 150) -> tuple[dict[str, dict], dict[str, float]]:
    """Run every stage once, uninterrupted; returns its arrays and wall times."""
    refs, times = {}, {}
    for name, args in stage_commands(root, train_steps).items():
        t = time.time()
        rc, err = launch.run([*args, "--out", root / f"{name}.h5"])
        assert rc == 0, err
        times[name] = time.time() - t
        refs[name] = arrays_of(root / f"{name}.h5")
    return refs, times


def kill_and_rerun(
    root: Path,
    launch: Launcher,
    name: str,
    args: list,
    ref: dict,
    duration: float,
    rng: np.random.Generator,
    stats: FaultStats,
) -> None:
    """One fault: start the command, SIGKILL it at a random moment of its expected run, check, re-run."""
    out = root / f"{name}-killed.h5"
    if out.exists():
        out.unlink()
    delay = float(rng.uniform(0.3, max(duration, 0.6)))
    stats.delays.append(delay)
    proc = launch.start([*args, "--out", out])
    time.sleep(delay)
    proc.kill()
    if proc.wait() not in (0, -signal.SIGKILL):  # it failed on its own before the kill: a broken harness or command
        stats.failed_before_kill += 1
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
    rc, _ = launch.run([*args, "--out", out, *extra])
    if rc != 0 or not same_arrays(arrays_of(out), ref):
        stats.rerun_mismatch += 1


def run_faults(
    root: Path, launch: Launcher, kills_per_stage: int, seed: int = 0, train_steps: int = 150
) -> dict[str, FaultStats]:
    root.mkdir(parents=True, exist_ok=True)
    refs, times = reference(root, launch, train_steps)
    rng = np.random.default_rng(seed)
    stats = {}
    for name, args in stage_commands(root, train_steps).items():
        st = stats[name] = FaultStats()
        for _ in range(kills_per_stage):
            kill_and_rerun(root, launch, name, args, refs[name], times[name], rng, st)
    return stats


def crash_before_rename(root: Path, launch: Launcher, train_steps: int = 150) -> dict[str, bool]:
    """CDRB_CRASH_BEFORE_RENAME=1 kills each writer between writing and renaming: the previous artifact (the
    reference run's) must survive byte for byte."""
    out = {}
    env = dict(os.environ, CDRB_CRASH_BEFORE_RENAME="1")
    for name, args in stage_commands(root, train_steps).items():
        target = root / f"{name}.h5"
        before = target.read_bytes()
        rc, _ = launch.run([*args, "--out", target, "--force"], env=env)
        intact = rc != 0 and target.read_bytes() == before
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
    ap.add_argument("--warm", action="store_true", help="fork each command from a warm server (Linux)")
    args = ap.parse_args()
    root = args.workdir or Path(tempfile.mkdtemp(prefix="cdrb-faults-"))
    root.mkdir(parents=True, exist_ok=True)
    t = time.time()
    with launcher(root, args.warm) as launch:
        stats = run_faults(root, launch, args.kills, args.seed)
        crashed = crash_before_rename(root, launch)
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
