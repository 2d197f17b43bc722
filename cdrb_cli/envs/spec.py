"""The EnvSpec: everything an artifact needs to rebuild and check its environment.

Every artifact embeds the EnvSpec it was made for, so a later stage can rebuild the exact environment and refuse
inputs made for another one. The spec is generic: a state vector of any dimension, a set of axis-aligned box
obstacles over some of its dimensions (the maze walls, or later Fetch walls), and a goal given in the positions.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from cdrb_cli.schema_base import Record

MAP_CHARS = {"#": "wall", ".": "free", "S": "start", "G": "goal", "C": "start and goal"}


MAX_MAP_SIDE = 100
MAX_BOXES = 20_000


class MazeLayout(Record):
    """A grid maze: ``rows`` of ``#`` wall, ``.`` free, ``S`` start cell, ``G`` goal cell, ``C`` start+goal cell."""

    name: str = Field(max_length=200)
    rows: list[str] = Field(min_length=3, max_length=MAX_MAP_SIDE)
    cell_size: float = Field(1.0, gt=0, le=100)

    @field_validator("rows")
    @classmethod
    def _check_rows(cls, rows: list[str]) -> list[str]:
        width = len(rows[0])
        if not 3 <= width <= MAX_MAP_SIDE or any(len(r) != width for r in rows):
            raise ValueError(f"rows must all have the same length, 3..{MAX_MAP_SIDE}")
        if any(ch not in MAP_CHARS for r in rows for ch in r):
            raise ValueError(f"rows may only contain {''.join(MAP_CHARS)}")
        return rows

    @property
    def n_rows(self) -> int:
        return len(self.rows)

    @property
    def n_cols(self) -> int:
        return len(self.rows[0])


class BoxObstacles(Record):
    """Axis-aligned boxes over the state dimensions ``dims``. A state collides when the point made of those
    dimensions is closer than ``inflate`` to any box (the agent's own radius), or lies outside ``[low, high]``."""

    dims: list[int] = Field(min_length=1, max_length=16)
    centers: list[list[float]] = Field(max_length=MAX_BOXES)
    half_sizes: list[list[float]] = Field(max_length=MAX_BOXES)
    inflate: float = Field(0.0, ge=0)
    low: list[float]
    high: list[float]

    @model_validator(mode="after")
    def _check_shapes(self) -> BoxObstacles:
        d = len(self.dims)
        if len(self.centers) != len(self.half_sizes):
            raise ValueError("centers and half_sizes must have the same length")
        if any(len(c) != d for c in self.centers) or any(len(h) != d for h in self.half_sizes):
            raise ValueError("every box needs one center and half size per dimension in dims")
        if len(self.low) != d or len(self.high) != d or any(lo >= hi for lo, hi in zip(self.low, self.high)):
            raise ValueError("low/high must give one increasing bound per dimension")
        if any(h < 0 for hs in self.half_sizes for h in hs):
            raise ValueError("half sizes must be non-negative")
        return self


class EnvSpec(Record):
    id: str = Field(
        max_length=200, description="environment id, e.g. 'maze-tight', or 'map:<name>' for a --maze-map file"
    )
    family: Literal["pointmaze"] = "pointmaze"
    obs_dim: int = Field(gt=0, le=1024)
    action_dim: int = Field(gt=0, le=1024)
    goal_dim: int = Field(gt=0, le=1024)
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
        if any(not 0 <= d < self.obs_dim for d in self.obstacles.dims):
            raise ValueError("obstacles.dims must index the state")
        if self.horizon > 100_000 or self.episode_limit > 10_000_000:
            raise ValueError("horizon / episode_limit out of range")
        return self

    @property
    def plan_env_steps(self) -> int:
        """Environment steps covered by a plan of the default horizon."""
        return self.horizon * self.plan_stride
