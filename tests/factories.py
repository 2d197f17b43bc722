"""Small, valid artifacts of every kind, built directly (no training), for format and fault tests."""

from __future__ import annotations

import contextlib
import json

import h5py
import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.configs import (
    ClusterConfig,
    ClusterSummary,
    CollectConfig,
    CollectSummary,
    EvalConfig,
    EvalSummary,
    PlanConfig,
    PlanSummary,
    SeedResult,
    TrainConfig,
    TrainState,
    UNetConfig,
)
from cdrb_cli.envs.pointmaze.controllers import PDConfig
from cdrb_cli.envs.pointmaze.expert import PlannerExpertConfig
from cdrb_cli.envs.registry import make_spec
from cdrb_cli.methods.cdrb import CDRBParams

KINDS = ("demos", "buffer", "model", "plans", "eval")


def spec():
    return make_spec("maze-tight")


def build(kind: str, rng: np.random.Generator | None = None, n: int = 5, seed: int = 0):
    """(manifest, arrays) for a valid artifact of ``kind``; ``n`` scales the array sizes."""
    rng = rng or np.random.default_rng(seed)
    env = spec()
    f32 = lambda *shape: rng.standard_normal(shape).astype(np.float32)
    if kind == "demos":
        lengths = rng.integers(2, 6, size=n)
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        N = int(lengths.sum())
        cfg = CollectConfig(env=env.id, episodes=n, expert=PlannerExpertConfig(), seed=seed)
        summ = CollectSummary(
            episodes=n,
            steps=N,
            success_rate=1.0,
            mean_length=float(lengths.mean()),
            max_length=int(lengths.max()),
            states_in_walls=0,
            train_episodes=n,
            valid_episodes=0,
            routes={"1,1": {"N": n}},
            wall_time_s=0.1,
        )
        arrays = {
            "steps/observations": f32(N, 4),
            "steps/actions": f32(N, 2),
            "steps/desired_goals": f32(N, 2),
            "episodes/start": starts.astype(np.int64),
            "episodes/length": lengths.astype(np.int64),
            "episodes/seed": rng.integers(0, 2**31 - 1, size=n),
            "episodes/success": np.ones(n, dtype=bool),
            "episodes/valid": np.zeros(n, dtype=bool),
        }
        return artifacts.make_manifest("demos", env=env, config=cfg, seed=seed, summary=summ), arrays
    if kind == "buffer":
        cfg = ClusterConfig(k=n, seed=seed)
        summ = ClusterSummary(points=n, source_states=10 * n, feature_dim=4, diameter=1.5, inertia=0.3, wall_time_s=0.1)
        arrays = {
            "points": np.clip(f32(n, 4), -1, 1),
            "source_index": rng.integers(0, 10 * n, size=n),
            "normalizer/low": -np.ones(4, np.float32),
            "normalizer/high": np.ones(4, np.float32),
        }
        return artifacts.make_manifest("buffer", env=env, config=cfg, seed=seed, summary=summ), arrays
    if kind == "model":
        cfg = TrainConfig(
            method=CDRBParams(d_max=2.0, diffusion_steps=8),
            net=UNetConfig(dim=8, dim_mults=[1, 2]),
            preset="quick",
            features="state",
            horizon=8,
            stride=2,
            steps=max(10, n),
            batch_size=4,
            lr=1e-3,
            ema_decay=0.99,
            ema_start=2,
            ema_every=1,
            checkpoint_every=5,
            seed=seed,
        )
        arrays = {
            "weights/net/layer.weight": f32(n, 3),
            "weights/net/layer.bias": f32(n),
            "ema/net/layer.weight": f32(n, 3),
            "ema/net/layer.bias": f32(n),
            "normalizer/low": -np.ones(4, np.float32),
            "normalizer/high": np.ones(4, np.float32),
            "curve/step": np.arange(1, n + 1, dtype=np.int64),
            "curve/loss": np.abs(f32(n)),
            "buffer/points": np.clip(f32(n, 4), -1, 1),
        }
        return artifacts.make_manifest(
            "model", env=env, config=cfg, seed=seed, state=TrainState(step=max(10, n), finished=True)
        ), arrays
    if kind == "plans":
        P, H = n, 8
        cfg = PlanConfig(sampler="paper", n=1, seed=seed)
        summ = PlanSummary(
            pairs=P,
            plans=P,
            in_wall_fraction=0.0,
            plans_with_wall_states=0,
            seconds_per_batch=0.1,
            seconds_per_plan=0.01,
            device="cpu",
        )
        arrays = {
            "plans": f32(P, H, 4),
            "pair_index": np.arange(P, dtype=np.int64),
            "starts": f32(P, 4),
            "goals": f32(P, 4),
            "in_wall": np.zeros((P, H), dtype=bool),
        }
        return artifacts.make_manifest("plans", env=env, config=cfg, seed=seed, summary=summ, method="cdrb"), arrays
    if kind == "eval":
        E = n
        cfg = EvalConfig(
            episodes=E,
            seeds=[0],
            controller=PDConfig(),
            sampler="paper",
            protocol="centre-start/corner-goal",
            seed=seed,
        )
        per = SeedResult(
            seed=0,
            episodes=E,
            success_rate=1.0,
            in_wall_fraction=0.0,
            executed_collision_rate=0.0,
            path_length_ratio=1.0,
            plan_seconds=0.1,
        )
        summ = EvalSummary(
            method="cdrb",
            model_preset="quick",
            success_mean=1.0,
            success_std=0.0,
            in_wall_mean=0.0,
            in_wall_std=0.0,
            executed_collision_mean=0.0,
            path_length_ratio_mean=1.0,
            plan_seconds_mean=0.1,
            per_seed=[per],
            wall_time_s=1.0,
        )
        arrays = {
            "episodes/seed": np.zeros(E, dtype=np.int64),
            "episodes/episode_seed": rng.integers(0, 2**31 - 1, size=E),
            "episodes/success": np.ones(E, dtype=bool),
            "episodes/steps": rng.integers(1, 300, size=E),
            "episodes/final_distance": np.abs(f32(E)),
            "episodes/plan_in_wall_fraction": np.zeros(E, np.float32),
            "episodes/plan_crosses_obstacle": np.zeros(E, dtype=bool),
            "episodes/plan_max_jump": np.abs(f32(E)),
            "episodes/plan_step_limit": np.full(E, 0.14, np.float32),
            "episodes/executed_collision": np.zeros(E, dtype=bool),
            "episodes/path_length": np.abs(f32(E)),
            "episodes/expert_path_length": np.abs(f32(E)),
            "episodes/plan_seconds": np.abs(f32(E)),
            "episodes/failure": np.zeros(E, dtype=np.int64),  # all successes
            "episodes/start": f32(E, 4),
            "episodes/goal": f32(E, 2),
        }
        return artifacts.make_manifest("eval", env=env, config=cfg, seed=seed, summary=summ), arrays
    raise KeyError(kind)


def write(path, kind: str, **kw):
    manifest, arrays = build(kind, **kw)
    artifacts.save(path, kind, manifest, arrays)
    return path


@contextlib.contextmanager
def tampered(path):
    """Open an artifact for editing with h5py, and afterwards re-sign its content checksum as a hostile writer
    would (the checksum catches damage, it is no signature): tests of deeper checks edit files through this."""
    from cdrb_cli.artifacts.core import CHECKSUM_ATTR, content_sha256

    with h5py.File(path, "r+") as f:
        yield f
        try:
            sizes = []
            f.visititems(lambda n, o: sizes.append(o.size * o.dtype.itemsize) if isinstance(o, h5py.Dataset) else None)
            if sum(sizes) > 2**26:  # a size bomb: the reader refuses it before the checksum
                return
            payload = bytes(f["manifest"][()])
            arrays = {}
            f.visititems(
                lambda n, o: arrays.__setitem__(n, o[()]) if isinstance(o, h5py.Dataset) and n != "manifest" else None
            )
            f.attrs[CHECKSUM_ATTR] = content_sha256(payload, arrays)
        except Exception:  # something the reader refuses before the checksum anyway
            pass


def edit_manifest(f, edit) -> None:
    """Apply ``edit`` to the JSON manifest of the open artifact ``f`` (inside :func:`tampered`, which re-signs)."""
    manifest = json.loads(bytes(f["manifest"][()]))
    edit(manifest)
    del f["manifest"]
    f["manifest"] = np.bytes_(json.dumps(manifest).encode())


class RandomActions:
    """A policy of uniform random actions in [-1, 1]^act_dim."""

    def __init__(self, act_dim: int):
        self.act_dim = act_dim

    def reset(self, n, rng):
        pass

    def act(self, states, goals, rng):
        return rng.uniform(-1, 1, size=(len(states), self.act_dim))


def run_doc_block(text: str, heading: str, sizes: dict[str, str], cwd, extra_env=None, timeout: int = 900):
    """Run the first ```bash block after ``heading`` (a regex) of a docs page as written, with only the
    ``sizes`` patterns replaced (each must occur, so a page edited away from them fails), with the test's Python
    environment's ``cdrb`` first on PATH (on Linux its commands forked from a warm server: tests/warm_shell.py);
    returns the finished process (stdout, stderr)."""
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    script = re.search(heading + r".*?```bash\n(.*?)```", text, re.S).group(1)
    for pattern, small in sizes.items():
        assert re.search(pattern, script), pattern
        script = re.sub(pattern, small, script)
    from tests.warm_shell import warm_cdrb

    with warm_cdrb() if sys.platform.startswith("linux") else contextlib.nullcontext(None) as shim:
        path = os.pathsep.join([*([str(shim)] if shim else []), str(Path(sys.executable).parent), os.environ["PATH"]])
        env = dict(os.environ, PATH=path, **(extra_env or {}))
        return subprocess.run(
            ["bash", "-euo", "pipefail", "-c", script],
            cwd=cwd,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
