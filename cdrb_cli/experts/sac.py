"""Goal-conditioned stable-baselines3 SAC (+HER) experts for PointMaze (the paper's expert type).

``train_sac`` trains one (``cdrb expert train``); ``SacExpert`` rolls one out inside ``cdrb collect --expert sac``.
Policies are stored in stable-baselines3's own zip format. Note: loading an SB3 zip unpickles parts of it, so cdrb
loads policies only from a path the user names on the command line, never from inside an artifact; the demos
artifact records the policy's sha256.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cdrb_cli import ui
from cdrb_cli.envs.pointmaze import CELL_CODES, import_gymnasium_robotics
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput


def _training_env(spec: EnvSpec, seed: int):
    gym = import_gymnasium_robotics()
    maze_map = [[CELL_CODES[c] for c in row] for row in spec.maze.rows]
    env = gym.make(
        "PointMaze_UMaze-v3",
        maze_map=maze_map,
        continuing_task=False,
        reward_type="sparse",
        max_episode_steps=spec.episode_limit,
    )
    env.unwrapped.position_noise_range = spec.position_noise
    env.reset(seed=seed)
    return env


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

    def reset(self, start_xy, goal_xy, rng: np.random.Generator) -> None:
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
        return bool(np.linalg.norm(obs[self.spec.goal_dims] - goal) <= self.spec.success_radius)
