"""OGBench's PointMaze agent, simulated with MuJoCo directly (the same model and step as the ``ogbench`` package,
without its gymnasium wrapper).

The agent is a sphere of radius 0.7 m on two slide joints (x, y) over a floor, among 4 x 4 x 2 m wall boxes; the
motors only declare the action space. A step moves the position by 0.2 x the action (each component clipped to
[-1, 1]), zeroes the velocity, then runs 5 MuJoCo steps of 0.02 s (RK4), in which contacts push a sphere that moved
into a wall back out. The state is the position (x, y). A reset puts the agent at its start cell's centre plus
U(-1, 1) m per axis, and the goal at its cell's centre plus the same kind of noise.
"""

from __future__ import annotations

import numpy as np

from cdrb_cli.envs.family import Episode
from cdrb_cli.envs.ogbench.maze import OGBenchGeometry
from cdrb_cli.envs.spec import EnvSpec

AGENT_RADIUS = 0.7
ACTION_SCALE = 0.2
FRAME_SKIP = 5
TIMESTEP = 0.02
#: half-width of the uniform noise (m, per axis) OGBench adds to start and goal cell centres
RESET_NOISE = 1.0


def model_xml(geometry: OGBenchGeometry) -> str:
    """The MJCF of a maze: the point agent of OGBench's point.xml and one box per wall cell."""
    walls = "\n".join(
        f'    <geom name="wall_{i}_{j}" type="box" pos="{x:g} {y:g} 1" size="2 2 1" contype="1" conaffinity="1" '
        'rgba="0.7 0.5 0.3 1"/>'
        for (i, j), (x, y) in ((tuple(c), geometry.cell_to_xy(c)) for c in np.argwhere(~geometry.free))
    )
    w, h = geometry.n_cols, geometry.n_rows
    return f"""<mujoco model="ogbench-pointmaze">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP}" integrator="RK4"/>
  <default>
    <joint limited="false" armature="0" damping="0"/>
    <geom condim="3" conaffinity="0" friction="1 0.5 0.5" density="100"/>
  </default>
  <worldbody>
    <light pos="0 0 40" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" pos="{2 * (w - 3):g} {2 * (h - 3):g} 0" size="{2 * w:g} {2 * h:g} 0.2"
      conaffinity="1" rgba="0.9 0.9 0.9 1"/>
{walls}
    <body name="torso" pos="0 0 0">
      <geom name="pointbody" type="sphere" size="{AGENT_RADIUS}" pos="0 0 {AGENT_RADIUS}" rgba="0.2 0.4 0.9 1"/>
      <joint name="ballx" type="slide" axis="1 0 0" pos="0 0 0"/>
      <joint name="bally" type="slide" axis="0 1 0" pos="0 0 0"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="ballx" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="bally" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>"""


class PointMazeOG:
    """One OGBench PointMaze: ``reset(episode)`` then ``step(action)`` repeatedly; states are (x, y)."""

    def __init__(self, spec: EnvSpec):
        import mujoco

        self.spec = spec
        self.geometry = OGBenchGeometry(spec.scene.maze)
        self.model = mujoco.MjModel.from_xml_string(model_xml(self.geometry))
        self.data = mujoco.MjData(self.model)
        self._step = mujoco.mj_step
        self._forward = mujoco.mj_forward
        self.goal = np.zeros(2)

    def place(self, xy) -> None:
        """Put the agent at rest at ``xy``."""
        self.data.qpos[:] = np.asarray(xy, dtype=np.float64)[:2]
        self.data.qvel[:] = 0.0
        self._forward(self.model, self.data)

    def reset(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng(int(episode.seed))
        start = self.geometry.cell_to_xy(episode.start[-2:]) + rng.uniform(-RESET_NOISE, RESET_NOISE, 2)
        self.goal = self.geometry.cell_to_xy(episode.goal[-2:]) + rng.uniform(-RESET_NOISE, RESET_NOISE, 2)
        self.place(start)
        return self.data.qpos.copy(), self.goal.copy()

    def step(self, action) -> np.ndarray:
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.data.qpos[:] = self.data.qpos + ACTION_SCALE * a
        self.data.qvel[:] = 0.0
        self._forward(self.model, self.data)
        self._step(self.model, self.data, nstep=FRAME_SKIP)
        return self.data.qpos.copy()

    def set_state(self, state) -> None:
        self.place(state)

    def close(self) -> None:
        pass
