"""gymnasium-robotics PointMaze built from an EnvSpec, with a small, fast episode API.

The stock environment is used unchanged (same MuJoCo model, dynamics and reset noise); cdrb only chooses the
start and goal cells, seeds the reset, and measures success itself (within ``spec.success_radius`` at any step),
so episodes never end early: plans are executed to the end and experts may come to rest at the goal.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np

from cdrb_cli.envs.maze import MazeGeometry
from cdrb_cli.envs.spec import EnvSpec

CELL_CODES = {"#": 1, ".": 0, "S": "r", "G": "g", "C": "c"}


def import_gymnasium_robotics():
    """Import gymnasium + gymnasium_robotics, silencing the unrelated Adroit notice it prints on stderr."""
    with contextlib.redirect_stderr(io.StringIO()):
        import gymnasium
        import gymnasium_robotics

        gymnasium.register_envs(gymnasium_robotics)
    return gymnasium


class PointMaze:
    """One PointMaze instance. ``reset(seed, start_cell, goal_cell)`` then ``step(action)`` repeatedly."""

    def __init__(self, spec: EnvSpec, render_mode: str | None = None):
        if spec.maze is None:
            raise ValueError("PointMaze needs an EnvSpec with a maze layout")
        gym = import_gymnasium_robotics()
        self.spec = spec
        self.geometry = MazeGeometry(spec.maze)
        maze_map = [[CELL_CODES[c] for c in row] for row in spec.maze.rows]
        kwargs = dict(maze_map=maze_map, continuing_task=True, reset_target=False, max_episode_steps=spec.episode_limit)
        if render_mode:
            kwargs["render_mode"] = render_mode
        self._wrapped = gym.make("PointMaze_UMaze-v3", **kwargs)
        self.env = self._wrapped.unwrapped
        self.env.position_noise_range = spec.position_noise
        self.goal = np.zeros(2)

    def reset(self, seed: int, start_cell, goal_cell) -> tuple[np.ndarray, np.ndarray]:
        obs, _ = self.env.reset(
            seed=int(seed), options={"reset_cell": tuple(map(int, start_cell)), "goal_cell": tuple(map(int, goal_cell))}
        )
        self.goal = np.array(obs["desired_goal"], dtype=np.float64)
        return np.array(obs["observation"], dtype=np.float64), self.goal.copy()

    def step(self, action) -> np.ndarray:
        obs, *_ = self.env.step(np.asarray(action, dtype=np.float64))
        return np.array(obs["observation"], dtype=np.float64)

    def set_state(self, state) -> None:
        """Place the ball at ``state`` = (x, y, vx, vy) (used by tests and controllers' checks)."""
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
