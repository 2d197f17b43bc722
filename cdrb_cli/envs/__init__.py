"""Task side: environment families (:mod:`cdrb_cli.envs.family`), their registry, the generic EnvSpec and obstacle
geometry, and pictures. Each family lives in a subpackage (``pointmaze/``)."""

from cdrb_cli.envs.spec import BoxObstacles, EnvSpec

__all__ = ["EnvSpec", "BoxObstacles"]
