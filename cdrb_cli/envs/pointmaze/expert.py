"""The scripted maze expert.

1. Route: a shortest 4-connected grid path from the start cell to the goal cell, with uniformly random tie-breaks
   at every step (so symmetric routes, e.g. the two gaps next to a corner goal, are both used: the data is
   multimodal).
2. Smoothing: greedy line-of-sight shortcuts between path points that keep ``clearance`` from every wall box.
3. Control: track a desired velocity that points at the current waypoint, with a speed profile that brakes for
   turns and comes to rest at the goal (``u = clip(gain (v_des - v))``). The episode ends once the ball rests at the
   goal, so every demonstration ends in the state a plan's goal is pinned to: (goal, zero velocity).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.family import ExpertConfig, ExpertEntry
from cdrb_cli.envs.geometry import box_distance
from cdrb_cli.envs.pointmaze.maze import MazeGeometry
from cdrb_cli.envs.registry import EXPERTS
from cdrb_cli.envs.spec import EnvSpec


class PlannerExpertConfig(ExpertConfig):
    """The scripted maze expert: randomized shortest grid path, line-of-sight smoothing, speed-profiled pursuit."""

    kind: Literal["planner"] = "planner"
    max_speed: float = Field(6.0, gt=0, description="cruise speed, m/s (the env clips each axis at 5)")
    max_accel: float = Field(18.0, gt=0, description="braking deceleration used for the speed profile, m/s^2")
    gain: float = Field(3.0, gt=0, description="velocity-tracking gain (action per m/s of error)")
    clearance: float = Field(0.3, ge=0, description="minimum distance kept from wall boxes when smoothing, m")
    switch_radius: float = Field(0.6, gt=0, description="distance at which a waypoint counts as passed, m")
    stop_gain: float = Field(10.0, gt=0, description="speed per metre of distance on the final approach, 1/s")
    settle_radius: float = Field(0.05, gt=0, description="episode ends once this close to the goal...")
    settle_speed: float = Field(0.1, gt=0, description="...and slower than this, m/s")


#: how many path points ahead a shortcut may reach: beyond the longest shortest path of every built-in map (31
#: cells), and a bound on the smoothing's work on large maps (a straight run longer than this keeps a waypoint on
#: the way, which the pursuit passes at full speed)
SHORTCUT_WINDOW = 64


def random_shortest_path(geom: MazeGeometry, start_cell, goal_cell, rng: np.random.Generator) -> list[tuple[int, int]]:
    dist = geom.bfs(goal_cell)
    cell = (int(start_cell[0]), int(start_cell[1]))
    if dist[cell] < 0:
        raise ValueError(f"goal cell {tuple(goal_cell)} is unreachable from {cell}")
    path = [cell]
    while dist[cell] > 0:
        options = [n for n in geom.neighbours(cell) if dist[n] == dist[cell] - 1]
        cell = options[int(rng.integers(len(options)))]
        path.append(cell)
    return path


class MazeExpert:
    """Goal-reaching expert for a PointMaze EnvSpec. Call :meth:`reset` once per episode, then :meth:`act`."""

    def __init__(self, spec: EnvSpec, config: PlannerExpertConfig | None = None):
        self.spec = spec
        self.cfg = config or PlannerExpertConfig()
        self.geom = MazeGeometry(spec.scene.maze)
        self.centers, self.halves = self.geom.wall_boxes
        self.waypoints = np.zeros((0, 2))
        self.speed_cap = np.zeros(0)
        self.k = 0
        self.cells: list[tuple[int, int]] = []

    # ----------------------------------------------------------------- route
    def _segment_clear(self, a: np.ndarray, b: np.ndarray, clearance: float | None = None) -> bool:
        """Whether every point of the segment a-b (sampled every 5 cm) keeps ``clearance`` from the wall boxes."""
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / 0.05)) + 1)
        pts = a[None] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None]
        need = self.cfg.clearance if clearance is None else clearance
        if need <= 0:  # distances are never negative
            return True
        if need < 1e-9 * self.geom.s:  # within rounding of a wall's face: measured against every box, as defined
            return bool(box_distance(pts, self.centers, self.halves).min() >= need)
        # a sample inside a wall cell is at distance 0 (or within rounding of it, far below `need`): refused
        # without measuring (most long segments are)
        cells = self.geom.xy_to_cell(pts)
        rows, cols = self.geom.free.shape
        on_map = (cells[:, 0] >= 0) & (cells[:, 0] < rows) & (cells[:, 1] >= 0) & (cells[:, 1] < cols)
        if not self.geom.free[cells[on_map, 0], cells[on_map, 1]].all():
            return False
        # only the boxes within `need` of the segment's bounding box can come closer than `need` (the margin is
        # widened past rounding: a box kept in excess never changes the minimum)
        pad = need * (1 + 1e-9) + 1e-9 * (1 + float(np.abs(pts).max()))
        lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
        near = ((self.centers + self.halves >= lo) & (self.centers - self.halves <= hi)).all(axis=1)
        return not near.any() or bool(box_distance(pts, self.centers[near], self.halves[near]).min() >= need)

    def _smooth(self, pts: np.ndarray) -> np.ndarray:
        out = [pts[0]]
        i = 0
        while i < len(pts) - 1:
            j = min(len(pts) - 1, i + SHORTCUT_WINDOW)
            while j > i + 1 and not self._segment_clear(pts[i], pts[j]):
                j -= 1
            out.append(pts[j])
            i = j
        return np.array(out)

    def reset(self, state, goal_xy, rng: np.random.Generator) -> None:
        start_xy, goal_xy = np.asarray(state, float)[:2], np.asarray(goal_xy, float)
        start_cell = self.geom.xy_to_cell(start_xy)
        goal_cell = self.geom.xy_to_cell(goal_xy)
        self.cells = random_shortest_path(self.geom, start_cell, goal_cell, rng)
        pts = self.geom.cell_to_xy(np.array(self.cells))
        pts[0], pts[-1] = start_xy, goal_xy
        if len(pts) == 1:
            pts = np.stack([start_xy, goal_xy])
        self.waypoints = self._smooth(pts)
        self.speed_cap = self._speed_profile(self.waypoints)
        self.k = 1

    def _speed_profile(self, wp: np.ndarray) -> np.ndarray:
        """Speed allowed when passing each waypoint: slower for sharper turns, 0 at the goal, and never more than
        what still allows braking for the waypoints after it."""
        cfg = self.cfg
        n = len(wp)
        cap = np.full(n, cfg.max_speed)
        for i in range(1, n - 1):
            a, b = wp[i] - wp[i - 1], wp[i + 1] - wp[i]
            cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-9))
            turn = np.arccos(np.clip(cos, -1, 1))
            cap[i] = max(1.2, cfg.max_speed * (1.0 - turn / np.pi) ** 1.5)
        cap[-1] = 0.0
        for i in range(n - 2, -1, -1):
            seg = float(np.linalg.norm(wp[i + 1] - wp[i]))
            cap[i] = min(cap[i], np.sqrt(cap[i + 1] ** 2 + 2 * cfg.max_accel * seg))
        return cap

    # ----------------------------------------------------------------- control
    def act(self, obs: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        p, v = obs[:2], obs[2:4]
        last = len(self.waypoints) - 1
        # advance once near the waypoint, but only when the next one is in sight with a margin (else the ball would
        # cut a corner into a wall, e.g. when it starts beside a gap)
        while (
            self.k < last
            and np.linalg.norm(self.waypoints[self.k] - p) < cfg.switch_radius
            and self._segment_clear(p, self.waypoints[self.k + 1], clearance=cfg.clearance * 0.75)
        ):
            self.k += 1
        target = self.waypoints[self.k]
        delta = target - p
        d = float(np.linalg.norm(delta))
        speed = min(cfg.max_speed, np.sqrt(self.speed_cap[self.k] ** 2 + 2 * cfg.max_accel * d))
        if self.k == last:
            speed = min(speed, cfg.stop_gain * d)  # linear near the goal: a smooth stop without chattering
        v_des = speed * delta / (d + 1e-9)
        return np.clip(cfg.gain * (v_des - v), -1.0, 1.0)

    def settled(self, obs: np.ndarray, goal: np.ndarray) -> bool:
        return bool(
            np.linalg.norm(obs[:2] - goal) < self.cfg.settle_radius and np.linalg.norm(obs[2:4]) < self.cfg.settle_speed
        )


def _configure(policy: Path | None) -> PlannerExpertConfig:
    return PlannerExpertConfig()


EXPERTS.register(
    ExpertEntry(
        PlannerExpertConfig,
        MazeExpert,
        _configure,
        "scripted: a random shortest grid route, smoothed, tracked to rest at the goal",
    )
)
