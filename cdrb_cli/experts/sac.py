"""Goal-conditioned stable-baselines3 SAC (+HER) experts (the paper's expert type), for any family that provides a
goal-conditioned gymnasium env (``EnvFamily.make_gym_env``).

``train_sac`` trains one (``cdrb expert train``); ``SacExpert`` rolls one out inside ``cdrb collect --expert sac``.
Policies are stored in stable-baselines3's own zip format. Note: loading an SB3 zip unpickles parts of it, so cdrb
loads policies only from a path the user names on the command line, never from inside an artifact; the demos
artifact records the policy's sha256.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np

from cdrb_cli import ui
from cdrb_cli.envs.family import ExpertConfig, ExpertEntry
from cdrb_cli.envs.registry import EXPERTS, family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput


class SacExpertConfig(ExpertConfig):
    """A stable-baselines3 SAC policy zip from `cdrb expert train`, by path and sha256."""

    kind: Literal["sac"] = "sac"
    policy_path: str
    policy_sha256: str
    deterministic: bool = True


def _training_env(spec: EnvSpec, seed: int):
    return family_of(spec).make_gym_env(spec, seed)


def train_sac(spec: EnvSpec, steps: int, seed: int, out: Path, her: bool = True, learning_starts: int = 1000) -> Path:
    """Train a goal-conditioned SAC(+HER) expert for ``steps`` env steps and save it (atomically) to ``out``."""
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.callbacks import BaseCallback

    from cdrb_cli.artifacts import atomic_path

    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    env = _training_env(spec, seed)
    kwargs = {}
    if her:
        kwargs = dict(
            replay_buffer_class=HerReplayBuffer,
            replay_buffer_kwargs=dict(n_sampled_goal=4, goal_selection_strategy="future"),
        )
    model = SAC(
        "MultiInputPolicy",
        env,
        # HER samples goals from finished episodes: start learning only after the first full episode
        learning_starts=max(learning_starts, spec.episode_limit + 1),
        batch_size=256,
        gamma=0.99,
        seed=seed,
        device="cpu",
        verbose=0,
        **kwargs,
    )

    class _Progress(BaseCallback):
        def __init__(self, bar, task):
            super().__init__()
            self.bar, self.task = bar, task

        def _on_step(self) -> bool:
            self.bar.update(self.task, completed=self.num_timesteps)
            return True

    with ui.progress() as bar:
        task = bar.add_task("SAC expert", total=steps, info="")
        model.learn(total_timesteps=steps, callback=_Progress(bar, task))
    out = Path(out)
    with atomic_path(out) as tmp:
        model.save(str(tmp.with_suffix(".zip")))
        os.replace(tmp.with_suffix(".zip"), tmp)
    env.close()
    return out


class SacExpert:
    """Rolls out a trained SB3 policy; the episode ends at the first success (SAC policies do not come to rest)."""

    @classmethod
    def from_config(cls, spec: EnvSpec, config: SacExpertConfig) -> SacExpert:
        return cls(spec, config.policy_path, deterministic=config.deterministic)

    def __init__(self, spec: EnvSpec, policy_path: str | Path, deterministic: bool = True):
        from stable_baselines3 import SAC

        path = Path(policy_path)
        if not path.is_file():
            raise BadInput(
                f"--policy {path}: no such file", hint="train one with `cdrb expert train ENV --out expert.zip`"
            )
        try:  # SB3 needs an env to rebuild a model trained with a HerReplayBuffer
            self.model = SAC.load(str(path), env=_training_env(spec, 0), device="cpu")
        except Exception as exc:
            raise BadInput(
                f"--policy {path}: not a stable-baselines3 SAC policy zip ({type(exc).__name__})",
                hint="pass a file written by `cdrb expert train`",
            ) from None
        space = self.model.observation_space
        try:
            dims = (space["observation"].shape[0], space["desired_goal"].shape[0])
        except (KeyError, TypeError, AttributeError):
            dims = None
        if dims != (spec.obs_dim, spec.goal_dim):
            raise BadInput(
                f"--policy {path}: policy observes {dims}, "
                f"but {spec.id} has (obs {spec.obs_dim}, goal {spec.goal_dim})",
                hint="train the expert on this environment",
            )
        self.spec = spec
        self.deterministic = deterministic
        self.goal = np.zeros(spec.goal_dim)

    def reset(self, state, goal_xy, rng: np.random.Generator) -> None:
        self.goal = np.asarray(goal_xy, dtype=np.float64)

    def act(self, obs: np.ndarray) -> np.ndarray:
        o = {
            "observation": obs.astype(np.float64),
            "achieved_goal": obs[self.spec.goal_dims].astype(np.float64),
            "desired_goal": self.goal,
        }
        action, _ = self.model.predict(o, deterministic=self.deterministic)
        return np.asarray(action, dtype=np.float64)

    def settled(self, obs: np.ndarray, goal: np.ndarray) -> bool:
        return bool(family_of(self.spec).success(self.spec, obs, goal))


def configure(policy: Path | None) -> SacExpertConfig:
    """The expert config of ``cdrb collect --expert sac --policy FILE``."""
    from cdrb_cli.artifacts import sha256_file

    if policy is None:
        raise BadInput("--expert sac needs --policy FILE", hint="train one with `cdrb expert train ENV`")
    if not Path(policy).is_file():
        raise BadInput(f"--policy {policy}: no such file", hint="train one with `cdrb expert train ENV`")
    return SacExpertConfig(policy_path=str(Path(policy).resolve()), policy_sha256=sha256_file(policy))


EXPERTS.register(ExpertEntry(SacExpertConfig, SacExpert.from_config, configure, "a stable-baselines3 SAC(+HER) policy"))
