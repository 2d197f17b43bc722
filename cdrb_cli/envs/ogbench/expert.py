"""OGBench's noisy PointMaze expert, the demonstrator of its ``navigate`` and ``stitch`` datasets.

Each step it looks up the oracle subgoal (the centre of the neighbouring cell one step closer to the goal by a
4-connected grid search from the goal cell; the current cell's centre inside the goal cell) and moves toward it at
full speed: the action is the unit vector to the subgoal plus Gaussian noise (std ``noise`` per component), clipped
to [-1, 1]. In ``navigate`` data a new goal is drawn from the maze's vertex cells (with the reset's noise) each time
the agent comes within the success radius of the current one; in ``stitch`` data the goal stays and the agent hovers
there until the episode ends. Episodes always run their full length (``EnvFamily.collect_limit``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.family import ExpertConfig, ExpertEntry
from cdrb_cli.envs.ogbench.env import RESET_NOISE
from cdrb_cli.envs.ogbench.maze import OGBenchGeometry
from cdrb_cli.envs.registry import EXPERTS
from cdrb_cli.envs.spec import EnvSpec


class OGBenchExpertConfig(ExpertConfig):
    """OGBench's noisy oracle-subgoal expert (its data-generation script's settings for PointMaze)."""

    kind: Literal["ogbench-noisy"] = "ogbench-noisy"
    noise: float = Field(0.5, ge=0, le=10, description="std of the Gaussian action noise per component")
    redraw_goals: bool | None = Field(
        None,
        description="draw a new goal from the vertex cells on each success (OGBench's navigate data); None: as the "
        "environment's dataset says (navigate: yes, stitch: no)",
    )


class OGBenchExpert:
    def __init__(self, spec: EnvSpec, cfg: OGBenchExpertConfig):
        self.spec, self.cfg = spec, cfg
        self.geometry = OGBenchGeometry(spec.scene.maze)
        redraw = cfg.redraw_goals
        self.redraw = spec.scene.dataset == "navigate" if redraw is None else redraw
        self.goal = np.zeros(2)
        self.rng = np.random.default_rng(0)

    def reset(self, state: np.ndarray, goal: np.ndarray, rng: np.random.Generator) -> None:
        self.goal, self.rng = np.asarray(goal, dtype=np.float64)[:2].copy(), rng

    def act(self, state: np.ndarray) -> np.ndarray:
        xy, g = np.asarray(state, dtype=np.float64)[:2], self.geometry
        if self.redraw and np.linalg.norm(xy - self.goal) <= self.spec.success_radius:
            cell = g.vertex_cells[int(self.rng.integers(len(g.vertex_cells)))]
            self.goal = g.cell_to_xy(cell) + self.rng.uniform(-RESET_NOISE, RESET_NOISE, 2)
        sub = g.cell_to_xy(g.toward(g.xy_to_cell(xy), g.xy_to_cell(self.goal)))
        direction = (sub - xy) / (np.linalg.norm(sub - xy) + 1e-6)
        return np.clip(direction + self.rng.normal(0.0, self.cfg.noise, 2), -1.0, 1.0)

    def settled(self, state: np.ndarray, goal: np.ndarray) -> bool:
        return False  # OGBench's episodes run their full length


def _configure(policy: Path | None) -> OGBenchExpertConfig:
    return OGBenchExpertConfig()


EXPERTS.register(
    ExpertEntry(
        OGBenchExpertConfig,
        OGBenchExpert,
        _configure,
        "OGBench's noisy oracle-subgoal expert (navigate: goals re-drawn on success; stitch: one goal 4 cells away)",
    )
)
