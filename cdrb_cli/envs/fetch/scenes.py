"""Fetch scene changes: boxes put down on or above the table after the data were collected.

A scene file (TOML) lists the boxes, each an axis-aligned box by its centre and half sizes in metres, and may name
the change (else the file's stem names it)::

    name = "reach-closed-x-plus"
    [[boxes]]
    center = [1.455, 0.749, 0.47]
    half = [0.005, 0.125, 0.30]

`cdrb plan` / `cdrb eval --scene FILE` run a model trained in the stock scene among them: the boxes are MuJoCo
geoms (they are physics) and obstacles of every collision test, while the task itself (its walls, which side of
them a point is on, the routes the data took) stays the training scene's. ``--protocol detour`` then draws the
pairs whose shortest route in the training scene a new box blocks (:func:`blocks_shortest_route`).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from pydantic import Field, ValidationError

from cdrb_cli.envs.fetch.geometry import MAX_OPENING, Box, gripper_obstacles
from cdrb_cli.envs.geometry import in_boxes
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.schema_base import Record
from cdrb_cli.settings import clip

MAX_SCENE_BYTES = 64 * 1024
#: no box reaches further than this from the origin, nor is larger than this in any half size, m (the table is
#: 1.3 m from the robot's base; a box of metres is a mistake)
MAX_COORD, MAX_HALF = 5.0, 1.0
HINT = "write [[boxes]] tables with center = [x, y, z] and half = [hx, hy, hz] in metres (docs/cli.md)"


class SceneChange(Record):
    """Boxes put down after the data were collected, and the change's name."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
    boxes: list[Box] = Field(min_length=1, max_length=16)


def default_name(path: Path, source: str) -> str:
    """The name of a scene file that does not set one: its file name without the extension, each character a name
    may not hold made a ``-``, without the leading characters a name may not start with (a dot, a dash, an
    underscore), at most 64 characters; one line naming the file when nothing is left."""
    name = re.sub(r"[^A-Za-z0-9._-]", "-", path.stem).lstrip("._-")[:64]
    if not name:
        raise BadInput(
            f"{source}: the scene is named after its file, and {clip(path.name, 80)!r} has no ASCII letter or "
            "digit to name it (a scene's name is A-Z, a-z, 0-9, '.', '_', '-')",
            hint='rename the file (e.g. closed-x.toml), or set name = "..." in it',
        )
    return name


def load_scene_change(path: str | Path, flag: str = "--scene") -> SceneChange:
    """A scene file, read through the guarded reader and checked; every problem is one line naming ``flag``."""
    from cdrb_cli.files import parse_toml, read_input_text

    path = Path(path)
    source = f"{flag} {path}"
    text = read_input_text(path, flag, MAX_SCENE_BYTES, "scene file", "pass a TOML file of [[boxes]]")
    data = parse_toml(text, source, hint=HINT)
    if "name" not in data:
        data["name"] = default_name(path, source)
    for i, box in enumerate(data.get("boxes", []) if isinstance(data.get("boxes"), list) else []):
        for key in ("center", "half"):
            value = box.get(key) if isinstance(box, dict) else None
            numbers = isinstance(value, list) and all(type(v) in (int, float) for v in value)
            if value is not None and not (numbers and len(value) == 3):
                raise BadInput(f"{source}: boxes[{i}].{key}: expected three numbers [x, y, z]", hint=HINT)
    try:
        change = SceneChange.model_validate(data)  # numbers checked above; lists become tuples
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err.get("loc", ()))
        msg = f"unknown key {key!r}" if err.get("type") == "extra_forbidden" else f"{key}: {err.get('msg', 'invalid')}"
        raise BadInput(f"{source}: {clip(msg, 160)}", hint=HINT) from None
    for i, box in enumerate(change.boxes):
        if any(abs(v) > MAX_COORD for v in box.center):
            raise BadInput(f"{source}: boxes[{i}].center beyond {MAX_COORD:g} m", hint=HINT)
        if any(not 0 < h <= MAX_HALF for h in box.half):
            raise BadInput(f"{source}: boxes[{i}].half: each half size in (0, {MAX_HALF:g}] m", hint=HINT)
    return change


def with_boxes(spec: EnvSpec, change: SceneChange, source: str) -> EnvSpec:
    """``spec``'s task among ``change``'s boxes (replacing any boxes the spec already had): the id becomes
    ``<task id>+<change name>``; one line naming ``source`` when a box covers the gripper's home (every episode
    starts there)."""
    from cdrb_cli.envs.fetch.geometry import body_obstacles

    scene = spec.scene
    opening = MAX_OPENING if scene.task == "pick-place" else 0.0
    for i, box in enumerate(change.boxes):
        if in_boxes(np.asarray(scene.home), gripper_obstacles([box], opening)):
            raise BadInput(
                f"{source}: boxes[{i}] overlaps the gripper at its home {tuple(round(v, 3) for v in scene.home)}, "
                "where every episode starts",
                hint="move the box away from the start (the gripper link is 13 cm wide and reaches 18 cm up)",
            )
    base = spec.id.removesuffix(f"+{scene.change}") if scene.change else spec.id
    new = scene.model_copy(update={"extra_boxes": list(change.boxes), "change": change.name})
    out = spec.model_copy(
        update={"id": f"{base}+{change.name}"[:200], "scene": new, "obstacles": body_obstacles(new.solid, new.task)[0]}
    )
    _check_arm_clear(out, source)
    return out


def _check_arm_clear(spec: EnvSpec, source: str) -> None:
    """Refuse boxes that the robot's arm (not only its gripper) penetrates where every episode starts: measured in
    the simulator after its reset, since the state's collision test models the gripper alone."""
    from cdrb_cli.envs.family import Episode
    from cdrb_cli.envs.fetch.env import FetchEnv
    from cdrb_cli.envs.fetch.tasks import MIN_DRAW_RATE, draw_task, task_draw_rate

    n_walls = len(spec.scene.walls)
    rate = task_draw_rate(spec.scene)  # one lucky draw is not enough: every episode seed must find its task
    if rate < MIN_DRAW_RATE:
        raise BadInput(
            f"{source}: the boxes leave (almost) no room to draw a start and a goal of {spec.id.split('+')[0]} "
            f"({100 * rate:.2g}% of candidate draws kept, fewer than {100 * MIN_DRAW_RATE:g}%)",
            hint="use smaller boxes, or put them where the task's blocks and goals are not drawn",
        )
    start, goal = draw_task(spec.scene, np.random.default_rng(0))
    env = FetchEnv(spec)
    try:
        env.reset(Episode(0, start, goal))
        hits = [(i - n_walls, body) for i, body in env.robot_contacts() if i >= n_walls]
    finally:
        env.close()
    if hits:
        i, body = hits[0]
        raise BadInput(
            f"{source}: boxes[{i}] cuts through the robot's {body.removeprefix('robot0:')} where every episode starts",
            hint="move the box clear of the arm (the arm reaches above and behind the gripper)",
        )


def blocks_shortest_route(spec: EnvSpec, start: np.ndarray, goal: np.ndarray) -> bool:
    """Whether a box of ``spec.scene.extra_boxes`` blocks the shortest route the scripted expert's router finds
    from ``start`` to ``goal`` (the carried point: the grip site for Reach, the block otherwise) in the training
    scene: the pair needs a detour the data did not take."""
    from cdrb_cli.envs.fetch.expert import FetchExpertConfig, routers

    scene = spec.scene
    if not scene.extra_boxes:
        return False
    config = FetchExpertConfig()
    carried = 0 if scene.task == "reach" else 1
    trained = routers(scene, scene.walls, config)[carried]
    new = routers(scene, scene.extra_boxes, config)[carried]
    a, b = np.asarray(start, float), np.asarray(goal, float)
    options = trained.options(a, b, ["over", "around"]) or {"direct": [b]}
    path = min(([a, *map(np.asarray, way)] for way in options.values()), key=_length)
    return any(new.blocked(p, q, end_legs=True) for p, q in zip(path, path[1:]))


def _length(points) -> float:
    return float(sum(np.linalg.norm(q - p) for p, q in zip(points, points[1:])))
