"""Goal-conditioned stable-baselines3 SAC (+HER) experts (the paper's expert type), for any family that provides a
goal-conditioned gymnasium env (``EnvFamily.make_gym_env``).

``train_sac`` trains one (``cdrb expert train``); ``SacExpert`` rolls one out inside ``cdrb collect --expert sac``.
Policies are stored in stable-baselines3's own zip format. SB3 pickles some entries of it (spaces, schedules,
classes); cdrb loads a zip without unpickling anything: it replaces every pickled entry with a value built from the
environment (SB3's ``custom_objects``), refuses a zip with a pickled entry it does not know, and SB3 reads the
weights with ``torch.load(weights_only=True)``. What a user still trusts in a zip: that its weights are the expert
they mean. The demos artifact records the policy's sha256.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import ClassVar, Literal

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
    flag_fields: ClassVar[tuple[str, ...]] = ("policy_path", "policy_sha256")  # from --policy (the file, hashed)

    def describe(self) -> str:
        return f"SAC policy {self.policy_path} (sha256 {self.policy_sha256[:12]})"


def _training_env(spec: EnvSpec, seed: int):
    return family_of(spec).make_gym_env(spec, seed)


def train_sac(spec: EnvSpec, steps: int, seed: int, out: Path, her: bool = True, learning_starts: int = 1000) -> Path:
    """Train a goal-conditioned SAC(+HER) expert for ``steps`` env steps and save it (atomically) to ``out``."""
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger

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

    # a logger that writes nothing: SB3's default one makes an empty folder in the temp directory for every run
    model.set_logger(Logger(None, []))
    with ui.progress() as bar:
        task = bar.add_task("SAC expert", total=steps, info="")
        model.learn(total_timesteps=steps, callback=_Progress(bar, task))
    out = Path(out)
    with atomic_path(out) as tmp:
        model.save(str(tmp.with_suffix(".zip")))
        os.replace(tmp.with_suffix(".zip"), tmp)
    env.close()
    return out


#: what cdrb puts in place of the entries SB3 pickles into a SAC zip (none is needed to act)
_PICKLED = {
    "policy_class",
    "observation_space",
    "action_space",
    "lr_schedule",
    "train_freq",
    "replay_buffer_class",
    "_last_obs",
    "_last_episode_starts",
    "_last_original_obs",
    "ep_info_buffer",
    "ep_success_buffer",
}


def _replacements(path: Path, spec: EnvSpec) -> dict:
    """SB3's ``custom_objects`` for a SAC zip: a value for every entry it stored pickled (cloudpickle) in its
    ``data`` JSON, built here from the environment, so that loading unpickles nothing. The policy weights are read
    by SB3 with ``torch.load(weights_only=True)``. A zip with a pickled entry cdrb does not know is refused."""
    import json
    import zipfile

    from stable_baselines3.common.buffers import DictReplayBuffer
    from stable_baselines3.sac.policies import MultiInputPolicy

    try:
        with zipfile.ZipFile(path) as z:
            data = json.loads(z.read("data"))
    except (zipfile.BadZipFile, KeyError, ValueError, OSError) as exc:
        raise BadInput(
            f"--policy {path}: not a stable-baselines3 SAC policy zip ({type(exc).__name__})",
            hint="pass a file written by `cdrb expert train`",
        ) from None
    if not isinstance(data, dict):
        raise BadInput(
            f"--policy {path}: not a stable-baselines3 SAC policy zip", hint="pass a file of `cdrb expert train`"
        )
    pickled = {k for k, v in data.items() if isinstance(v, dict) and ":serialized:" in v}
    unknown = sorted(pickled - _PICKLED)
    if unknown:
        raise BadInput(
            f"--policy {path}: holds pickled entries cdrb will not load ({', '.join(unknown)[:200]})",
            hint="pass a file written by `cdrb expert train`",
        )
    env = _training_env(spec, 0)
    rate = data.get("learning_rate", 3e-4)
    rate = float(rate) if isinstance(rate, (int, float)) else 3e-4
    custom = {
        "policy_class": MultiInputPolicy,
        "observation_space": env.observation_space,
        "action_space": env.action_space,
        "lr_schedule": lambda _: rate,
        "train_freq": (1, "step"),
        # acting needs no replay buffer: a one-slot one, and no HER (which would need the env)
        "replay_buffer_class": DictReplayBuffer,
        "replay_buffer_kwargs": {},
        "buffer_size": 1,
        "_last_obs": None,
        "_last_episode_starts": None,
        "_last_original_obs": None,
        "ep_info_buffer": None,
        "ep_success_buffer": None,
    }
    env.close()
    return custom


class SacExpert:
    """Rolls out a trained SB3 policy; the episode ends at the first success (SAC policies do not come to rest)."""

    @classmethod
    def from_config(cls, spec: EnvSpec, config: SacExpertConfig) -> SacExpert:
        return cls(spec, config.policy_path, deterministic=config.deterministic)

    def __init__(self, spec: EnvSpec, policy_path: str | Path, deterministic: bool = True):
        from stable_baselines3 import SAC

        from cdrb_cli.artifacts.core import check_input_file

        path = check_input_file(policy_path, "--policy", MAX_POLICY_BYTES, "policy zip", POLICY_HINT)
        custom = _replacements(path, spec)  # every pickled entry of the zip, replaced: nothing is unpickled
        import warnings

        try:
            with warnings.catch_warnings():  # a damaged zip makes torch and SB3 warn before they fail: one line only
                warnings.simplefilter("ignore")
                self.model = SAC.load(str(path), env=None, device="cpu", custom_objects=custom)
        except Exception as exc:
            raise BadInput(
                f"--policy {path}: not a stable-baselines3 SAC policy zip for {spec.id} ({type(exc).__name__})",
                hint="pass a file written by `cdrb expert train` for this environment",
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


#: an SB3 SAC zip for these tasks is a few MB; a file far larger is not one
MAX_POLICY_BYTES = 1 << 30
POLICY_HINT = "train one with `cdrb expert train ENV --out expert.zip`"


def configure(policy: Path | None) -> SacExpertConfig:
    """The expert config of ``cdrb collect --expert sac --policy FILE``."""
    from cdrb_cli.artifacts import sha256_file

    if policy is None:
        raise BadInput("--expert sac needs --policy FILE", hint="train one with `cdrb expert train ENV`")
    from cdrb_cli.artifacts.core import check_input_file

    check_input_file(policy, "--policy", MAX_POLICY_BYTES, "policy zip", POLICY_HINT)
    return SacExpertConfig(policy_path=str(Path(policy).resolve()), policy_sha256=sha256_file(policy))


EXPERTS.register(ExpertEntry(SacExpertConfig, SacExpert.from_config, configure, "a stable-baselines3 SAC(+HER) policy"))
