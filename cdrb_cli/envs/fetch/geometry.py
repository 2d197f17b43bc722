"""Fetch collision geometry: walls as boxes, the gripper and the object as boxes around their observed positions.

The Fetch state gives the grip site's position (state[0:3]) and, with an object, the block's centre (state[3:6]).
A state is *in an obstacle* when a part of the gripper or the block overlaps a wall, or when either leaves the
workspace (the gripper below the table top, the block off the table). The gripper is a union of axis-aligned
boxes fixed relative to the grip site (the env fixes its orientation; Pick & Place's fingers widen with the
opening the state records), so "a part overlaps a wall" is "the grip site lies in the wall grown by that part" (a
Minkowski sum of two boxes is a box). The block may be turned about z, so it counts by its inscribed ball: its
centre may not come within 2.5 cm of a wall (a rounded box). The tests are the generic ones
(:func:`cdrb_cli.envs.geometry.in_boxes`, :func:`~cdrb_cli.envs.geometry.path_crosses_boxes`) over those boxes,
vectorized over any batch of states or paths, including the straight steps between consecutive states.

The extents are the axis-aligned bounds of the MuJoCo collision meshes at the env's fixed gripper orientation,
measured from the model (docs/environments.md), less a contact tolerance: contacts let bodies rest a few
millimetres into each other, and a state the simulator reached by pushing against a wall is not a collision.
"""

from __future__ import annotations

import functools

import numpy as np

from cdrb_cli.envs.geometry import box_distance, in_boxes, path_crosses_boxes, segment_box_distance
from cdrb_cli.envs.spec import BoxObstacles
from cdrb_cli.schema_base import Record

#: table top (z) and the table's x-y extent, from gymnasium-robotics' fetch/shared.xml (table0: centre
#: (1.3, 0.75, 0.2), half size (0.25, 0.35, 0.2))
TABLE_TOP = 0.4
TABLE_XY = ((1.05, 1.55), (0.40, 1.10))
#: the block's half size (fetch/push.xml: a 5 cm cube)
BLOCK_HALF = 0.025
#: how far bodies may rest into each other in contact without it counting as a collision, m
CONTACT_TOLERANCE = 0.004

#: the gripper as boxes relative to the grip site, (low, high) per axis: the two fingers (closed) and the gripper
#: link above them; measured from the collision meshes. Each finger slides up to 5 cm out (state entries
#: ``finger_l``/``finger_r``): Pick & Place's finger box widens with the opening its state records; Reach and Push
#: lock the fingers closed.
FINGERS_CLOSED = ((-0.016, -0.016, -0.019), (0.016, 0.016, 0.059))
GRIPPER_LINK = ((-0.047, -0.064, 0.049), (0.043, 0.064, 0.178))
MAX_OPENING = 0.05
#: Pick & Place states: the two finger openings
FINGER_DIMS = (9, 10)
#: openings are rounded up to this step for the collision test (a few millimetres conservative)
OPENING_STEP = 0.005
#: the grip site may not come closer than this to the table top (the finger tips would be in it)
GRIP_ABOVE_TABLE = 0.010
#: the reach of the gripper's workspace (x, y, z) for the grip site
GRIP_WORKSPACE = ((0.95, 0.25, TABLE_TOP + GRIP_ABOVE_TABLE), (1.75, 1.25, 1.10))


class Box(Record):
    """An axis-aligned box: centre and half sizes (x, y, z), metres."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]

    @property
    def low(self) -> np.ndarray:
        return np.asarray(self.center) - np.asarray(self.half)

    @property
    def high(self) -> np.ndarray:
        return np.asarray(self.center) + np.asarray(self.half)


def grown(walls: list[Box], part_low, part_high, shrink: float) -> tuple[list[list[float]], list[list[float]]]:
    """Centres and half sizes of the walls grown by a part (positions where the part overlaps a wall)."""
    centers, halves = [], []
    lo, hi = np.asarray(part_low, dtype=float), np.asarray(part_high, dtype=float)
    for w in walls:
        low = w.low - hi + shrink
        high = w.high - lo - shrink
        centers.append(((low + high) / 2).tolist())
        halves.append(np.maximum((high - low) / 2, 0.0).tolist())
    return centers, halves


def fingers(opening: float) -> tuple[tuple, tuple]:
    """The finger box with each finger slid ``opening`` metres out."""
    (x0, y0, z0), (x1, y1, z1) = FINGERS_CLOSED
    return (x0, y0 - opening, z0), (x1, y1 + opening, z1)


def gripper_obstacles(walls: list[Box], opening: float = 0.0, dims=(0, 1, 2), margin: float = 0.0) -> BoxObstacles:
    """Where the grip site may not be: every wall grown by every gripper part, the fingers ``opening`` metres open
    (and by ``margin``: a clearance test); the workspace bounds the rest."""
    centers, halves = [], []
    for lo, hi in (fingers(opening), GRIPPER_LINK):
        c, h = grown(walls, lo, hi, CONTACT_TOLERANCE - margin)
        centers += c
        halves += h
    low, high = GRIP_WORKSPACE
    return BoxObstacles(dims=list(dims), centers=centers, half_sizes=halves, low=list(low), high=list(high))


def _finger_boxes(walls: list[Box], opening: float) -> tuple[np.ndarray, np.ndarray]:
    c, h = grown(walls, *fingers(opening), CONTACT_TOLERANCE)
    return np.asarray(c, dtype=np.float64).reshape(-1, 3), np.asarray(h, dtype=np.float64).reshape(-1, 3)


def _opening(states: np.ndarray) -> np.ndarray:
    """Per state, the wider finger's opening, rounded up to OPENING_STEP."""
    q = np.clip(np.max(np.asarray(states)[..., list(FINGER_DIMS)], axis=-1), 0.0, MAX_OPENING)
    return np.round(np.ceil(q / OPENING_STEP - 1e-9) * OPENING_STEP, 6)


def block_obstacles(walls: list[Box], dims=(3, 4, 5), margin: float = 0.0, rounded: bool = True) -> BoxObstacles:
    """Where the block's centre may not be: within its inscribed radius of a wall (the block may be turned about
    z, so only that ball is surely inside it; ``rounded=False``: the wall grown by the unturned block, a
    conservative box for planning routes), grown by ``margin``; off the table (or sunk into it) is outside the
    bounds."""
    if rounded:
        c = [list(w.center) for w in walls]
        h = [list(w.half) for w in walls]
        inflate = BLOCK_HALF - CONTACT_TOLERANCE + margin
    else:
        half = (BLOCK_HALF,) * 3
        c, h = grown(walls, [-v for v in half], half, CONTACT_TOLERANCE - margin)
        inflate = 0.0
    (x0, x1), (y0, y1) = TABLE_XY
    low = (x0, y0, TABLE_TOP)  # a centre below the table top: fallen off (pushes press it a few mm in)
    high = (x1, y1, 1.50)
    return BoxObstacles(dims=list(dims), centers=c, half_sizes=h, inflate=inflate, low=list(low), high=list(high))


def body_obstacles(walls: list[Box], task: str) -> list[BoxObstacles]:
    """The fixed obstacle sets a state of ``task`` is tested against: the gripper's (fingers closed) and the
    block's when there is one."""
    return list(_body_obstacles(tuple((tuple(w.center), tuple(w.half)) for w in walls), task))


@functools.lru_cache(maxsize=64)
def _body_obstacles(walls: tuple, task: str) -> tuple[BoxObstacles, ...]:
    """Built once per scene: every collision test of a collect or an eval reuses them."""
    boxes = [Box(center=c, half=h) for c, h in walls]
    out = [gripper_obstacles(boxes)]
    if task != "reach":
        out.append(block_obstacles(boxes))
    return tuple(out)


def states_in_obstacles(states: np.ndarray, walls: list[Box], task: str) -> np.ndarray:
    """Boolean over states (..., D): any body overlaps a wall or leaves its workspace."""
    return np.logical_or.reduce(list(states_in_obstacles_by_body(states, walls, task).values()))


def states_in_obstacles_by_body(states: np.ndarray, walls: list[Box], task: str) -> dict[str, np.ndarray]:
    """:func:`states_in_obstacles` for each body apart: ``gripper`` (closed, or opened as wide as the state has it)
    and, for a task with one, ``block``."""
    states = np.asarray(states)
    out = {
        name: np.asarray(in_boxes(states, ob), dtype=bool)
        for name, ob in zip(("gripper", "block"), body_obstacles(walls, task))
    }
    out["gripper"] = out["gripper"] | _open_fingers_in_walls(states, walls, task)
    return out


def _open_fingers_in_walls(states: np.ndarray, walls: list[Box], task: str) -> np.ndarray:
    """Boolean over states (..., D): Pick & Place's opened fingers, as wide as each state has them, overlap a wall
    (the closed fingers are in :func:`body_obstacles`)."""
    out = np.zeros(states.shape[:-1], dtype=bool)
    if task != "pick-place" or not walls:
        return out
    opening = _opening(states)
    for q in np.unique(opening[opening > 0]):
        m = opening == q
        centers, halves = _finger_boxes(walls, float(q))
        out[m] = box_distance(states[m][..., :3].astype(np.float64), centers, halves) <= 0.0
    return out


def paths_in_obstacles(paths: np.ndarray, walls: list[Box], task: str, bounded: bool = True) -> np.ndarray:
    """Boolean over paths (..., T, D): a state in an obstacle, or a straight step between two states along which
    a body passes through a wall (for the fingers, as wide as the wider of the step's two states); ``bounded=False``:
    the walls alone, leaving the workspace not counted."""
    return np.logical_or.reduce(list(paths_in_obstacles_by_body(paths, walls, task, bounded).values()))


def paths_in_obstacles_by_body(
    paths: np.ndarray, walls: list[Box], task: str, bounded: bool = True
) -> dict[str, np.ndarray]:
    """:func:`paths_in_obstacles` for each body apart: ``gripper`` (closed, or opened as wide as the plan has it)
    and, for a task with one, ``block``."""
    paths = np.asarray(paths)
    out = {}
    for name, ob in zip(("gripper", "block"), body_obstacles(walls, task)):
        if not bounded:
            ob = ob.model_copy(update={"low": [-1e3] * len(ob.low), "high": [1e3] * len(ob.high)})
        out[name] = np.asarray(path_crosses_boxes(paths, ob), dtype=bool)  # its states too
    out["gripper"] = out["gripper"] | _open_fingers_in_walls(paths, walls, task).any(axis=-1)
    if task == "pick-place" and walls and paths.shape[-2] > 1:
        flat = paths.reshape(-1, *paths.shape[-2:])
        opening = _opening(flat)
        step = np.maximum(opening[:, :-1], opening[:, 1:])
        hit = np.zeros(flat.shape[0], dtype=bool)
        for q in np.unique(step[step > 0]):
            i, j = np.nonzero(step == q)
            centers, halves = _finger_boxes(walls, float(q))
            a, b = flat[i, j, :3].astype(np.float64), flat[i, j + 1, :3].astype(np.float64)
            d = segment_box_distance(a, b, centers, halves, within=1e-12)
            hit[i[d <= 0.0]] = True
        out["gripper"] = out["gripper"] | hit.reshape(out["gripper"].shape)
    return out
