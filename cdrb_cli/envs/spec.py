"""The EnvSpec: everything an artifact needs to rebuild and check its environment.

Every artifact embeds the EnvSpec it was made for, so a later stage can rebuild the exact environment and refuse
inputs made for another one. The spec is generic: a state vector of any dimension, the goal as some of its
dimensions, a set of axis-aligned box obstacles over some of its dimensions, and ``scene``, the part only its
family reads (for PointMaze: the map and the reset noise), typed by the family that registered it.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from cdrb_cli.envs.geometry import BoxObstacles  # noqa: F401  (part of the spec's public names)
from cdrb_cli.registry import Dispatch, Registry
from cdrb_cli.schema_base import Record

#: the built-in families' modules: importing one registers the family (envs.registry.FAMILIES) and its scene type
FAMILY_MODULES = {
    "pointmaze": "cdrb_cli.envs.pointmaze",
    "fetch": "cdrb_cli.envs.fetch",
    "ogbench": "cdrb_cli.envs.ogbench",
}


class Scene(Record):
    """Base of a family's own part of the EnvSpec (``spec.scene``); subclasses fix ``family``."""

    family: str


#: family name -> the type of its part of the spec, registered with the family itself (envs.registry.FAMILIES)
SCENES: Registry[type[Scene]] = Registry(
    "environment family", FAMILY_MODULES, key=lambda scene: scene.model_fields["family"].default
)


class EnvSpec(Record):
    id: str = Field(max_length=200, description="environment id, e.g. 'maze-tight', or 'map:<name>' for a map file")
    scene: Annotated[Scene, Dispatch(SCENES, key="family")] = Field(
        description="the family's own part of the spec; scene.family names the family"
    )
    obs_dim: int = Field(gt=0, le=1024)
    action_dim: int = Field(gt=0, le=1024)
    goal_dim: int = Field(gt=0, le=1024)
    state_labels: list[str]
    goal_dims: list[int] = Field(description="indices of the state that the goal is compared with")
    pinned_dims: list[int] | None = Field(
        None, description="indices of the state pinned at a plan's start (and goal); null: the whole state"
    )
    pinned_end_dims: list[int] | None = Field(
        None, description="indices of the state pinned at a plan's goal, when not pinned_dims; null: pinned_dims"
    )
    horizon: int = Field(gt=1, description="default plan length in planned states")
    plan_stride: int = Field(gt=0, description="environment steps per planned state")
    episode_limit: int = Field(gt=0, description="environment steps per episode")
    success_radius: float = Field(gt=0)
    dt: float = Field(gt=0, description="seconds per environment step")
    obstacles: BoxObstacles

    @model_validator(mode="after")
    def _check_dims(self) -> EnvSpec:
        if len(self.state_labels) != self.obs_dim:
            raise ValueError("state_labels must have obs_dim entries")
        if len(self.goal_dims) != self.goal_dim or any(not 0 <= d < self.obs_dim for d in self.goal_dims):
            raise ValueError("goal_dims must be goal_dim indices into the state")
        for name in ("pinned_dims", "pinned_end_dims"):
            dims = getattr(self, name)
            if dims is not None and (
                not dims or any(not 0 <= d < self.obs_dim for d in dims) or len(set(dims)) != len(dims)
            ):
                raise ValueError(f"{name} must be distinct indices into the state")
        if any(not 0 <= d < self.obs_dim for d in self.obstacles.dims):
            raise ValueError("obstacles.dims must index the state")
        if self.horizon > 100_000 or self.episode_limit > 10_000_000:
            raise ValueError("horizon / episode_limit out of range")
        return self

    @property
    def family(self) -> str:
        return self.scene.family

    @property
    def pin_dims(self) -> list[int]:
        """The state indices pinned at a plan's start (``pinned_dims``, or every state dimension)."""
        return list(range(self.obs_dim)) if self.pinned_dims is None else list(self.pinned_dims)

    @property
    def pin_end_dims(self) -> list[int]:
        """The state indices pinned at a plan's goal (``pinned_end_dims``, or the start's)."""
        return self.pin_dims if self.pinned_end_dims is None else list(self.pinned_end_dims)

    @property
    def plan_env_steps(self) -> int:
        """Environment steps covered by a plan of the default horizon."""
        return self.horizon * self.plan_stride
