"""Task side: environment specs, maze geometry, gymnasium construction, controllers, pictures."""

from cdrb_cli.envs.spec import BoxObstacles, EnvSpec, MazeLayout

__all__ = ["EnvSpec", "MazeLayout", "BoxObstacles"]
