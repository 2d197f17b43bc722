"""Scripted Fetch experts (one per task), with routes over or around the walls.

Every expert steers a *carried point* (the grip site for Reach, the block for Push and Pick & Place) along
waypoints with ``a[:3] = gain (target - point) / 0.05``, scaled as a whole into [-1, 1] (the env moves the gripper
by at most 5 cm per axis per step), and holds at the goal once there, so episodes have a fixed length and end at rest.

* **Routes.** When the straight segment to the next target passes a wall (grown by the body's extents and a
  clearance), the route goes *over* the walls (up above their top, across, down) or *around* one end of them
  (x beyond the end). The expert draws one of the routes that exist for its task at random (among those at most
  1.6 times as long as the shortest: no long detours), so the data holds
  both modes where both exist (Push: around either end of the short wall; Pick & Place: over the tall wall or
  around either end; Reach: out of the corridor over the walls or past either end).
* **Reach**: the gripper follows the route to the goal.
* **Push** (fingers locked): for the current block target t, d points from the block to a spot 5 cm ahead on the
  leg's line (pure pursuit: a block that drifted is steered back onto the line); the gripper goes to the pre-push
  point block - 0.06 d (travelling above the block, and above the wall when its way crosses it), descends to the
  block's height and pushes toward block + d min(|t - block|, 0.03), easing in near the goal, then lifts off; it
  re-approaches whenever it is no longer behind the block (lateral offset > 1.5 cm).
* **Pick & Place**: above the block (open) -> down -> close for 3 steps -> lift 8 cm -> carry the block along the
  route -> hold at the goal; a dropped block is picked up again.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from cdrb_cli.envs.family import ExpertConfig, ExpertEntry
from cdrb_cli.envs.fetch.geometry import MAX_OPENING, Box, block_obstacles, gripper_obstacles
from cdrb_cli.envs.fetch.tasks import side
from cdrb_cli.envs.geometry import box_arrays, segment_hits_boxes
from cdrb_cli.envs.registry import EXPERTS
from cdrb_cli.envs.spec import BoxObstacles, EnvSpec

STEP = 0.05  # metres per unit action
DETOUR = 1.6  # routes are drawn among those at most this much longer than the shortest
NEAR = 0.008  # the least clearance of a leg that starts or ends near a wall (execution strays a few mm)


class FetchExpertConfig(ExpertConfig):
    """The scripted Fetch experts: waypoint following with random routes over or around the walls."""

    kind: Literal["fetch-scripted"] = "fetch-scripted"
    gain: float = Field(1.0, gt=0, le=10, description="action per 5 cm of error")
    clearance: float = Field(0.03, ge=0, le=0.2, description="distance kept from the walls by routes, m")
    reach_tolerance: float = Field(0.015, gt=0, le=0.1, description="a waypoint counts as reached this close, m")
    routes: list[Literal["over", "around"]] = Field(
        default_factory=lambda: ["over", "around"],
        min_length=1,
        description="route kinds drawn from where they exist (each once)",
    )

    @field_validator("routes")
    @classmethod
    def _once(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError("list each route kind once")
        return value


def _move(point: np.ndarray, target: np.ndarray, gain: float) -> np.ndarray:
    """The action toward ``target``, scaled as a whole into [-1, 1] (clipping each axis alone would bend the way:
    a long leg up and a short one across would go across first)."""
    v = gain * (np.asarray(target, dtype=np.float64) - np.asarray(point, dtype=np.float64)) / STEP
    return v / max(1.0, float(np.abs(v).max()))


def _length(points: list[np.ndarray]) -> float:
    return float(sum(np.linalg.norm(q - p) for p, q in zip(points, points[1:])))


def _dedupe(points: list[np.ndarray]) -> list[np.ndarray]:
    """Waypoints without repeats (a zero-length leg would be judged as a middle leg)."""
    out = [points[0]]
    for p in points[1:]:
        if np.linalg.norm(p - out[-1]) > 1e-6:
            out.append(p)
    return out


class Router:
    """Waypoints for a point (the grip site or the block) among walls: ``hard`` is where its body overlaps a wall,
    ``soft`` the same grown by a clearance. Routes keep the clearance, except on the legs that leave the start
    and reach the end, which may lie closer to a wall than the clearance (a block next to a wall)."""

    def __init__(self, hard: list[BoxObstacles], soft: list[BoxObstacles], clearance: float, side=None):
        def stack(sets):
            arrays = [box_arrays(ob) for ob in sets]
            return np.concatenate([a[0] for a in arrays]), np.concatenate([a[1] for a in arrays])

        self.hard, self.soft = stack(hard), stack(soft)
        self.clearance = clearance
        self.side = side  # which side of the walls a point is on (None: unknown)

    @property
    def top(self) -> float:
        """The top of the clearance zone (z); -inf without walls."""
        centers, halves = self.soft
        return float((centers + halves)[:, 2].max()) if len(centers) else -np.inf

    def _hits(self, boxes, a: np.ndarray, b: np.ndarray) -> bool:
        centers, halves = boxes
        return segment_hits_boxes(a, b, centers, halves, 1e-9)

    def blocked(self, a: np.ndarray, b: np.ndarray, end_legs: bool = False) -> bool:
        """Does the segment pass a wall (within the clearance; only the walls themselves for a leg at an end)?"""
        return self._hits(self.hard if end_legs else self.soft, np.asarray(a, float), np.asarray(b, float))

    def _clear(self, legs: list[np.ndarray]) -> bool:
        n = len(legs) - 1
        return not any(self.blocked(legs[i], legs[i + 1], end_legs=i in (0, n - 1)) for i in range(n))

    def options(self, a, b, kinds) -> dict[str, list]:
        """Route name -> waypoints from ``a`` to ``b`` (ending at ``b``); {"direct": [b]} when the way is free."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        if not self.blocked(a, b):
            return {"direct": [b]}
        if self.side is not None and self.side(a) == self.side(b) and not self.blocked(a, b, end_legs=True):
            return {"direct": [b]}  # along a wall on one side of it: closer than the clearance, but free
        centers, halves = self.soft
        lo = (centers - halves).min(axis=0) - 0.005  # just outside the clearance zone
        hi = (centers + halves).max(axis=0) + 0.005
        out: dict[str, list] = {}
        if "over" in kinds:
            z = hi[2]
            route = _dedupe([np.array([a[0], a[1], max(a[2], z)]), np.array([b[0], b[1], max(b[2], z)]), b])
            if self._clear([a, *route]):
                out["over"] = route
        if "around" in kinds:
            # an end beside a wall's end (its y within the zone): turn where the clearance still holds, so the
            # last leg closes in on the wall gradually instead of running along it at the end legs' margin
            y_turn = b[1] if not lo[1] <= b[1] <= hi[1] else (lo[1] if b[1] < (lo[1] + hi[1]) / 2 else hi[1])
            for name, x in (("around x-", lo[0]), ("around x+", hi[0])):
                # keep the start's height past the end (low far corners are out of the arm's reach), then go
                for y in dict.fromkeys((y_turn, b[1])):
                    route = _dedupe([np.array([x, a[1], a[2]]), np.array([x, y, a[2]]), b])
                    if self._clear([a, *route]):
                        out[name] = route
                        break
        return out


def routers(scene, walls: list[Box], config: FetchExpertConfig) -> tuple[Router, Router]:
    """(the grip site's router, the carried or pushed block's router) among ``walls`` with ``config``'s clearance."""
    c = config.clearance
    opening = MAX_OPENING if scene.task == "pick-place" else 0.0  # routes keep room for open fingers
    sides = partial(side, scene)
    grip = partial(gripper_obstacles, walls, opening)
    grip_router = Router([grip(margin=NEAR)], [grip(margin=c)], c, sides)

    def blocks(margin):  # the unturned block: a box, conservative for routes
        return block_obstacles(walls, (0, 1, 2), margin=margin, rounded=False)

    if scene.task == "push":  # a pushed block drifts and the pusher rides beside it: 3 cm more
        return grip_router, Router([blocks(NEAR)], [blocks(c + 0.03)], c, sides)
    held = MAX_OPENING / 2  # a carried block: the block and the gripper holding it (the grip site at its centre)

    def carried(m):
        return [blocks(m), gripper_obstacles(walls, held, margin=m)]

    return grip_router, Router(carried(NEAR), carried(c), c, sides)


class _Base:
    def __init__(self, spec: EnvSpec, config: FetchExpertConfig):
        self.spec = spec
        self.cfg = config
        # every solid box of the scene: the expert of a changed scene routes around the boxes put down too
        self.grip_router, self.block_router = routers(spec.scene, spec.scene.solid, config)
        self.rng = np.random.default_rng(0)
        self.route_name = "direct"
        self.goal = np.zeros(3)

    def _pick_route(self, router: Router, a, b, kinds, fallback=("over", "around")) -> list[np.ndarray]:
        options = router.options(a, b, kinds)
        if not options:  # nothing clean among ``kinds``: another kind the body can take, else straight there
            others = [k for k in fallback if k not in kinds]
            options = (router.options(a, b, others) if others else {}) or {"direct": [np.asarray(b, float)]}
        length = {k: _length([np.asarray(a, float), *v]) for k, v in options.items()}
        shortest = min(length.values())
        names = sorted(k for k in options if length[k] <= DETOUR * shortest + 1e-9)  # no long detours
        self.route_name = names[int(self.rng.integers(len(names)))]
        return [np.asarray(p, float) for p in options[self.route_name]]

    def settled(self, state: np.ndarray, goal: np.ndarray) -> bool:
        return False  # fixed-length episodes: the expert holds at the goal until the episode limit


class ReachExpert(_Base):
    def reset(self, state, goal, rng: np.random.Generator) -> None:
        self.rng = rng
        self.goal = np.asarray(goal, float)
        self.waypoints = self._pick_route(self.grip_router, state[:3], self.goal, self.cfg.routes)

    def act(self, state: np.ndarray) -> np.ndarray:
        grip = state[:3]
        while len(self.waypoints) > 1 and np.linalg.norm(self.waypoints[0] - grip) < self.cfg.reach_tolerance:
            self.waypoints.pop(0)
        return np.append(_move(grip, self.waypoints[0], self.cfg.gain), 0.0)


class PushExpert(_Base):
    """Pushes the block along its route; the gripper travels above the block (and the wall) to get behind it."""

    BEHIND = 0.06  # pre-push distance behind the block centre: the fingers (1.6 cm) clear a turned block (3.5 cm)
    LIFT = 0.08  # travel height above the block centre
    PUSH = 0.03  # how far ahead of the block the pusher aims

    def reset(self, state, goal, rng: np.random.Generator) -> None:
        self.rng = rng
        self.goal = np.asarray(goal, float)
        block = state[3:6]
        # block route in the table plane: around an end of the wall (it cannot be pushed over it)
        self.targets = self._pick_route(self.block_router, block, self.goal, ["around"], fallback=())
        self.approach: list[np.ndarray] = []
        self.pushing = self.done = False
        self.leg: tuple[np.ndarray, np.ndarray] | None = None

    def _pursuit(self, block: np.ndarray, target: np.ndarray, dist: float) -> np.ndarray:
        """Push direction: toward a point 5 cm ahead on the leg's line (a block that drifted off it is steered back,
        so it does not graze the wall's end)."""
        start, end = self.leg
        line = end - start
        length = float(np.linalg.norm(line))
        if length < 1e-6 or dist < 0.05:
            ahead = target
        else:
            u = line / length
            t = float(np.clip((block - start) @ u + 0.05, 0.0, length))
            ahead = start + t * u
        delta = ahead - block
        return delta / max(float(np.linalg.norm(delta)), 1e-9)

    def pre_push(self, block: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Where the gripper goes down to push the block along ``d`` (x-y unit): :data:`BEHIND` behind its centre,
        just below it."""
        return np.array([*(block[:2] - self.BEHIND * d), block[2] - 0.005])

    def _behind(self, grip, block, d) -> bool:
        rel = grip[:2] - block[:2]
        along = float(rel @ d)
        lateral = float(np.linalg.norm(rel - along * d))
        return along < -0.02 and lateral < 0.015 and abs(grip[2] - block[2]) < 0.02

    def act(self, state: np.ndarray) -> np.ndarray:
        grip, block = state[:3], state[3:6]
        self.stuck = False  # set when there is no room behind the block for the next push (a controller may recover)
        while len(self.targets) > 1 and np.linalg.norm(self.targets[0][:2] - block[:2]) < 0.02:
            self.targets.pop(0)
        target = self.targets[0]
        if self.leg is None or np.linalg.norm(self.leg[1] - target[:2]) > 1e-9:
            self.leg = (block[:2].copy(), target[:2].copy())  # a new leg starts where the block is now
        delta = target[:2] - block[:2]
        dist = float(np.linalg.norm(delta))
        if self.done or (dist < 0.015 and len(self.targets) == 1):  # at the goal: lift the pusher off and hold
            self.done, self.pushing = True, False
            rest = np.array([grip[0], grip[1], max(block[2] + self.LIFT, self.grip_router.top + 0.005)])
            return np.append(_move(grip, rest, self.cfg.gain), 0.0)
        d = self._pursuit(block[:2], target[:2], dist)
        low_z = block[2] - 0.005
        if self.pushing and self._behind(grip, block, d):
            gain = 0.6 if len(self.targets) > 1 else 0.6 * float(np.clip(dist / 0.05, 0.3, 1.0))  # ease in: no slide
            aim = np.array([*(block[:2] + d * min(dist, self.PUSH)), low_z])
            return np.append(_move(grip, aim, gain * self.cfg.gain), 0.0)
        # (re-)approach: above the pre-push point, then down
        self.pushing = False
        pre = self.pre_push(block, d)
        above = pre + np.array([0.0, 0.0, self.LIFT])
        if self.grip_router.blocked(above, above):  # near the wall: come down from above its top
            above[2] = self.grip_router.top + 0.005
        if self.grip_router.blocked(pre, pre, end_legs=True):  # no room behind the block: wait above (a failure)
            self.stuck = True
            return np.append(_move(grip, above, self.cfg.gain), 0.0)
        if np.linalg.norm(grip[:2] - pre[:2]) < 0.012:
            if grip[2] - low_z < 0.008:
                self.pushing = True
            return np.append(_move(grip, pre, self.cfg.gain), 0.0)
        if not self.approach or np.linalg.norm(self.approach[-1] - above) > 0.01:
            start = grip if grip[2] >= above[2] - 0.01 else np.array([grip[0], grip[1], above[2]])
            way = self.grip_router.options(start, above, ["over"]) or {"direct": [above]}
            legs = [np.asarray(p, float) for p in next(iter(way.values()))]
            self.approach = ([start] if start is not grip else []) + legs
        while len(self.approach) > 1 and np.linalg.norm(self.approach[0] - grip) < self.cfg.reach_tolerance:
            self.approach.pop(0)
        aim = self.approach[0]
        if np.linalg.norm(grip[:2] - above[:2]) < 0.012:
            aim = pre
        return np.append(_move(grip, aim, self.cfg.gain), 0.0)


class PickPlaceExpert(_Base):
    """Grasp, lift, carry along the route, hold at the goal; re-grasp a dropped block."""

    ABOVE = 0.06
    LIFT = 0.08

    def reset(self, state, goal, rng: np.random.Generator) -> None:
        self.rng = rng
        self.goal = np.asarray(goal, float)
        self.phase = "approach"
        self.closing = 0
        self.carry: list[np.ndarray] = []
        self.approach: list[np.ndarray] = []

    def _holding(self, state) -> bool:
        grip, block = state[:3], state[3:6]
        width = state[9] + state[10]
        return bool(np.linalg.norm(block - grip) < 0.03 and width > 0.02)

    def act(self, state: np.ndarray) -> np.ndarray:
        grip, block = state[:3], state[3:6]
        if self.phase == "carry" and not self._holding(state):
            self.phase, self.approach = "approach", []
        if self.phase == "approach":
            above = block + np.array([0.0, 0.0, self.ABOVE])
            if not self.approach or np.linalg.norm(self.approach[-1] - above) > 0.01:
                way = self.grip_router.options(grip, above, ["over"]) or {"direct": [above]}
                self.approach = [np.asarray(p, float) for p in next(iter(way.values()))]
            while len(self.approach) > 1 and np.linalg.norm(self.approach[0] - grip) < self.cfg.reach_tolerance:
                self.approach.pop(0)
            if np.linalg.norm(grip[:2] - block[:2]) < 0.01 and abs(grip[2] - above[2]) < 0.02:
                self.phase = "descend"
            return np.append(_move(grip, self.approach[0], self.cfg.gain), 1.0)
        if self.phase == "descend":
            if np.linalg.norm(grip - block) < 0.01:
                self.phase, self.closing = "close", 0
            return np.append(_move(grip, block, self.cfg.gain), 1.0)
        if self.phase == "close":
            self.closing += 1
            if self.closing >= 3:
                lifted = block + np.array([0.0, 0.0, self.LIFT])
                self.carry = [lifted, *self._pick_route(self.block_router, lifted, self.goal, self.cfg.routes)]
                self.phase = "carry"
            return np.append(_move(grip, block, self.cfg.gain), -1.0)
        # carry: steer the block
        while len(self.carry) > 1 and np.linalg.norm(self.carry[0] - block) < self.cfg.reach_tolerance:
            self.carry.pop(0)
        return np.append(_move(block, self.carry[0], self.cfg.gain), -1.0)


def build(spec: EnvSpec, config: FetchExpertConfig):
    cls = {"reach": ReachExpert, "push": PushExpert, "pick-place": PickPlaceExpert}[spec.scene.task]
    return cls(spec, config)


def configure(policy: Path | None) -> FetchExpertConfig:
    return FetchExpertConfig()


EXPERTS.register(
    ExpertEntry(
        FetchExpertConfig, build, configure, "scripted Fetch experts: routes over or around the walls, random choice"
    )
)
