"""The EnvSpec: everything an artifact needs to rebuild and check its environment.

Every artifact embeds the EnvSpec it was made for, so a later stage can rebuild the exact environment and refuse
inputs made for another one. The spec is generic: a state vector of any dimension, a set of axis-aligned box
obstacles over some of its dimensions (the maze walls, or later Fetch walls), and a goal given in the positions.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from cdrb_cli.schema_base import Record

MAP_CHARS = {"#": "wall", ".": "free", "S": "start", "G": "goal", "C": "start and goal"}


class MazeLayout(Record):
    """A grid maze: ``rows`` of ``#`` wall, ``.`` free, ``S`` start cell, ``G`` goal cell, ``C`` start+goal cell."""

    name: str
    rows: list[str]
    cell_size: float = 1.0

    @property
    def n_rows(self) -> int:
        return len(self.rows)

    @property
    def n_cols(self) -> int:
        return len(self.rows[0])


class BoxObstacles(Record):
    """Axis-aligned boxes over the state dimensions ``dims``. A state collides when the point made of those
    dimensions is closer than ``inflate`` to any box (the agent's own radius), or lies outside ``[low, high]``."""

    dims: list[int]
    centers: list[list[float]]
    half_sizes: list[list[float]]
    inflate: float = 0.0
    low: list[float]
    high: list[float]


class EnvSpec(Record):
    id: str = Field(description="environment id, e.g. 'maze-tight', or 'map:<name>' for a --maze-map file")
    family: Literal["pointmaze"] = "pointmaze"
    obs_dim: int = Field(gt=0)
    action_dim: int = Field(gt=0)
    goal_dim: int = Field(gt=0)
    state_labels: list[str]
    goal_dims: list[int] = Field(description="indices of the state that the goal is compared with")
    horizon: int = Field(gt=1, description="default plan length in planned states")
    plan_stride: int = Field(gt=0, description="environment steps per planned state")
    episode_limit: int = Field(gt=0, description="environment steps per episode")
    success_radius: float = Field(gt=0)
    dt: float = Field(gt=0, description="seconds per environment step")
    obstacles: BoxObstacles
    maze: MazeLayout | None = None
    position_noise: float = Field(
        0.25, ge=0, description="uniform noise (per axis, in cells) added to start and goal cell centres at reset"
    )

    @model_validator(mode="after")
    def _check_dims(self) -> EnvSpec:
        if len(self.state_labels) != self.obs_dim:
            raise ValueError("state_labels must have obs_dim entries")
        if len(self.goal_dims) != self.goal_dim or any(not 0 <= d < self.obs_dim for d in self.goal_dims):
            raise ValueError("goal_dims must be goal_dim indices into the state")
        return self

    @property
    def plan_env_steps(self) -> int:
        """Environment steps covered by a plan of the default horizon."""
        return self.horizon * self.plan_stride
