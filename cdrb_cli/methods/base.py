"""The interface every planning method implements."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from cdrb_cli.buffer import Normalizer, feature_dim
from cdrb_cli.configs import TrainConfig
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.nets import build_net


@dataclass
class SampleResult:
    """Plans (P, H, F) in normalized space and, optionally, intermediate iterates [(k, (P, H, F))]."""

    plans: torch.Tensor
    iterates: list[tuple[int, torch.Tensor]] = field(default_factory=list)


class Method:
    """A planner over trajectories of ``horizon`` states with ``feature_dim`` features (the state first, then
    the action when ``features == "state-action"``), in normalized space. The first and last planned states are
    pinned to the start and goal states."""

    name = "base"
    samplers: tuple[str, ...] = ()

    def __init__(self, config: TrainConfig, spec: EnvSpec, normalizer: Normalizer, device="cpu"):
        self.config = config
        self.spec = spec
        self.normalizer = normalizer
        self.device = torch.device(device)
        self.obs_dim = spec.obs_dim
        self.feature_dim = feature_dim(spec, config.features)
        self.horizon = config.horizon
        self.net = build_net(config.net, self.feature_dim, self.horizon, cond_dim=self.obs_dim).to(self.device)

    # -------------------------------------------------------------- pinning
    def pin(self, x: torch.Tensor, start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """Overwrite the state part of the first and last planned states (a new tensor; exact copies)."""
        x = x.clone()
        x[:, 0, : self.obs_dim] = start
        x[:, -1, : self.obs_dim] = goal
        return x

    @staticmethod
    def ends(batch: torch.Tensor, obs_dim: int) -> tuple[torch.Tensor, torch.Tensor]:
        return batch[:, 0, :obs_dim], batch[:, -1, :obs_dim]

    # -------------------------------------------------------------- to implement
    def loss(self, batch: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        raise NotImplementedError

    def sample(
        self,
        net: torch.nn.Module,
        start: torch.Tensor,
        goal: torch.Tensor,
        rng: np.random.Generator,
        sampler: str | None = None,
        steps: int | None = None,
        keep_iterates: int = 0,
    ) -> SampleResult:
        raise NotImplementedError

    def extra_arrays(self) -> dict[str, np.ndarray]:
        """Arrays the model artifact must carry for sampling (e.g. the CDRB buffer)."""
        return {}


def keep_schedule(total: int, keep: int) -> set[int]:
    """Which of ``total`` iterations to keep as iterates (evenly spaced, ``keep`` of them)."""
    if keep <= 0 or total <= 0:
        return set()
    return {int(round(i)) for i in np.linspace(0, total - 1, min(keep, total))}
