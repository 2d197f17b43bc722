"""gymnasium-robotics PointMaze built from an EnvSpec, with a small, fast episode API.

The stock environment is used unchanged (same MuJoCo model, dynamics and reset noise); cdrb only chooses the
start and goal cells, seeds the reset, and measures success itself (within ``spec.success_radius`` at any step),
so episodes never end early: plans are executed to the end and experts may come to rest at the goal.
"""

from __future__ import annotations

import contextlib
import io
import os

import numpy as np

from cdrb_cli.envs.family import Episode
from cdrb_cli.envs.pointmaze.maze import MazeGeometry
from cdrb_cli.envs.spec import EnvSpec

CELL_CODES = {"#": 1, ".": 0, "S": "r", "G": "g", "C": "c"}


def import_gymnasium_robotics():
    """Import gymnasium + gymnasium_robotics, silencing the unrelated Adroit notice it prints on stderr."""
    with contextlib.redirect_stderr(io.StringIO()):
        import gymnasium
        import gymnasium_robotics

        gymnasium.register_envs(gymnasium_robotics)
    return gymnasium


def maze_map(spec: EnvSpec) -> list[list]:
    """The spec's layout in gymnasium-robotics' ``maze_map`` encoding."""
    return [[CELL_CODES[c] for c in row] for row in spec.scene.maze.rows]


def make_maze_env(gym, **kwargs):
    """``gym.make`` of gymnasium-robotics' PointMaze on a map. It writes the maze's MuJoCo XML to a file in the
    system temp folder and never removes it (one file per env made: thousands after a few evals); the model is
    compiled by then, so the file is removed here."""
    env = gym.make("PointMaze_UMaze-v3", **kwargs)
    xml = getattr(env.unwrapped, "tmp_xml_file_path", None)
    if xml:
        with contextlib.suppress(OSError):
            os.unlink(xml)
    return env


class PointMaze:
    """One PointMaze instance: ``reset(episode)`` then ``step(action)`` repeatedly."""

    def __init__(self, spec: EnvSpec, render_mode: str | None = None):
        gym = import_gymnasium_robotics()
        self.spec = spec
        self.geometry = MazeGeometry(spec.scene.maze)
        kwargs = dict(
            maze_map=maze_map(spec), continuing_task=True, reset_target=False, max_episode_steps=spec.episode_limit
        )
        if render_mode:
            kwargs["render_mode"] = render_mode
        self._wrapped = make_maze_env(gym, **kwargs)
        self.env = self._wrapped.unwrapped
        self.env.position_noise_range = spec.scene.position_noise
        self.goal = np.zeros(2)

    def reset(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        options = {"reset_cell": tuple(map(int, episode.start)), "goal_cell": tuple(map(int, episode.goal))}
        obs, _ = self.env.reset(seed=int(episode.seed), options=options)
        if not self.spec.scene.goal_noise:  # the same draws (so the same start), the goal at its cell centre
            self.env.goal = self.env.maze.cell_rowcol_to_xy(np.asarray(options["goal_cell"]))
            self.env.update_target_site_pos()
        self.goal = np.array(self.env.goal if not self.spec.scene.goal_noise else obs["desired_goal"], np.float64)
        return np.array(obs["observation"], dtype=np.float64), self.goal.copy()

    def step(self, action) -> np.ndarray:
        obs, *_ = self.env.step(np.asarray(action, dtype=np.float64))
        return np.array(obs["observation"], dtype=np.float64)

    def set_state(self, state) -> None:
        """Place the ball at ``state`` = (x, y, vx, vy) (used by tests and pictures)."""
        state = np.asarray(state, dtype=np.float64)
        self.env.point_env.set_state(state[:2].copy(), state[2:4].copy())

    def render(self):
        return self.env.render()

    @property
    def dynamics(self) -> dict[str, float]:
        """Mass, damping, actuator gear and time step of the ball (for exact inverse dynamics)."""
        m = self.env.point_env.model
        return {
            "mass": float(m.body_mass[1:].sum()),
            "damping": float(m.dof_damping[0]),
            "gear": float(m.actuator_gear[0, 0]),
            "dt": float(m.opt.timestep) * int(self.env.point_env.frame_skip),
        }

    def close(self) -> None:
        self._wrapped.close()


def training_env(spec: EnvSpec, seed: int):
    """The goal-conditioned gymnasium env RL experts train on: sparse reward, terminating on success."""
    gym = import_gymnasium_robotics()
    env = make_maze_env(
        gym,
        maze_map=maze_map(spec),
        continuing_task=False,
        reward_type="sparse",
        max_episode_steps=spec.episode_limit,
    )
    env.unwrapped.position_noise_range = spec.scene.position_noise
    env.reset(seed=seed)
    return env
