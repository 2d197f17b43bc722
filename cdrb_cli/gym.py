"""Every stock cdrb environment as a gymnasium env: ``import cdrb_cli.gym`` registers ``cdrb/<id>-v0`` for each id
`cdrb envs` lists (the mazes, the Fetch tasks with and without walls; ``cdrb/<id>`` for OGBench's ids, which end in
their own version), so ``gymnasium.make("cdrb/maze-tight-v0")``
works in any gymnasium loop (or, without the import, ``gymnasium.make("cdrb_cli.gym:cdrb/maze-tight-v0")``).

The env is cdrb's own simulator for the id (the same MuJoCo model, dynamics and reset noise as `cdrb eval`):
observations are cdrb's raw state vectors, actions the family's, the reward 1 on success (within the id's success
radius) and 0 otherwise, and an episode terminates on success and is truncated at the id's episode limit. A reset
draws its start and goal from the environment's evaluation protocol (``options={"episode": EPISODE}`` resets to a
given :class:`~cdrb_cli.envs.family.Episode`, e.g. one of `cdrb eval`'s pairs); ``info["goal"]`` is the goal.
``protocol`` (``gymnasium.make(id, protocol="official-code")``) is one of the family's (`cdrb envs --json`), with its
success radius, episode limit and noise as `cdrb eval --protocol` has them, and ``stream`` the pairs' stream (test,
tune or train). ``env.unwrapped.cdrb_spec`` is the environment's spec (its scene and obstacles) and
``env.unwrapped.collides(states)`` its collision test. Bad arguments, seeds, episodes and actions raise cdrb's
:class:`~cdrb_cli.errors.BadInput` with a one-line message."""

from __future__ import annotations

import re

import gymnasium
import numpy as np
from gymnasium import spaces

from cdrb_cli.errors import BadInput
from cdrb_cli.settings import clip

NAMESPACE = "cdrb"
VERSION = 0


def gym_id(env_id: str) -> str:
    """The gymnasium id of a cdrb environment id: ``cdrb/<id>-v0``, or ``cdrb/<id>`` for an id that already ends
    in a version (OGBench's names)."""
    if re.search(r"-v\d+$", env_id):
        return f"{NAMESPACE}/{env_id}"
    return f"{NAMESPACE}/{env_id}-v{VERSION}"


class CdrbEnv(gymnasium.Env):
    """One cdrb environment behind gymnasium's API (see the module's description)."""

    metadata = {"render_modes": []}

    def __init__(self, env_id: str, protocol: str | None = None, stream: str = "test", render_mode: str | None = None):
        from cdrb_cli.envs.registry import family_of, make_spec
        from cdrb_cli.seeding import EVAL_STREAMS

        base = make_spec(env_id)
        self.family = family_of(base)
        known = [p for p in self.family.protocols() if p not in self.family.scene_protocols]
        self.protocol = self.family.protocol if protocol is None else protocol
        if self.protocol not in known:
            raise BadInput(f"protocol = {clip(repr(protocol), 40)}: not a protocol of {env_id}",
                           hint=f"choose one of {', '.join(known)}")  # fmt: skip
        if stream not in EVAL_STREAMS:
            raise BadInput(f"stream = {clip(repr(stream), 40)}: not a stream", hint=f"choose {', '.join(EVAL_STREAMS)}")
        if render_mode is not None:
            raise BadInput(f"render_mode = {clip(repr(render_mode), 40)}: this env draws nothing",
                           hint="`cdrb eval --video DIR` writes rollout GIFs")  # fmt: skip
        self.render_mode = None
        self.cdrb_spec = self.family.protocol_spec(base, self.protocol)
        self._stream = EVAL_STREAMS[stream]
        spec = self.cdrb_spec
        self.observation_space = spaces.Box(-np.inf, np.inf, (spec.obs_dim,), np.float64)
        self.action_space = spaces.Box(-1.0, 1.0, (spec.action_dim,), np.float64)
        self._sim = None
        self.goal = np.zeros(spec.goal_dim)
        self._steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        from cdrb_cli.envs.family import Episode

        if seed is not None:
            if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**32:
                raise BadInput(f"seed = {clip(repr(seed), 40)}: not a seed", hint="pass a whole number in 0..2**32-1")
            seed = int(seed)
        if options is not None and not isinstance(options, dict):
            raise BadInput(f"options = {clip(repr(options), 40)}: not a dict", hint="pass options={'episode': EPISODE}")
        super().reset(seed=seed)
        episode = (options or {}).get("episode")
        given = episode is not None
        if not given:
            draw = int(self.np_random.integers(2**31)) if seed is None else seed
            episode = self.family.draw_protocol_episodes(self.cdrb_spec, 1, draw, self._stream, self.protocol)[0]
        elif not isinstance(episode, Episode):
            raise BadInput(f"options['episode'] = {clip(repr(episode), 40)}: not an Episode",
                           hint="pass one of cdrb's episodes (family.draw_episodes)")  # fmt: skip
        if self._sim is None:
            self._sim = self.family.make_env(self.cdrb_spec)
        try:
            state, goal = self._sim.reset(episode)
        except Exception as exc:  # the simulator's own checks (assertions, bad cells) on another family's episode
            why = clip(str(exc), 60) or type(exc).__name__
            raise BadInput(
                f"options['episode'] = {clip(repr(episode), 60)}: not an episode of this environment ({why})",
                hint="draw it for this id",
            ) from None
        state = np.asarray(state, np.float64)
        if given:  # a given episode: its start, and the goal reached from it
            at_goal = state.copy()
            at_goal[list(self.cdrb_spec.goal_dims)] = goal
            inside = self.family.in_collision(self.cdrb_spec, np.stack([state, at_goal]))
            if inside.any():
                which = "start" if inside[0] else "goal"
                raise BadInput(f"options['episode'] = {clip(repr(episode), 60)}: its {which} is inside an obstacle",
                               hint="choose a free start and goal")  # fmt: skip
        self.goal, self._steps = goal, 0
        return state, {"goal": np.array(self.goal), "episode": episode}

    def step(self, action):
        if self._sim is None:
            raise BadInput("step before reset (or after close)", hint="call env.reset() first")
        action = _numbers(action, "action", "an array of the action space's shape")
        if action.shape != self.action_space.shape:
            raise BadInput(f"action of shape {action.shape}: {self.action_space.shape} finite numbers expected",
                           hint="an array of the action space's shape")  # fmt: skip
        state = np.asarray(self._sim.step(action), np.float64)
        self._steps += 1
        success = bool(self.family.success(self.cdrb_spec, state, self.goal))
        truncated = self._steps >= self.cdrb_spec.episode_limit and not success
        return state, float(success), success, truncated, {"goal": np.array(self.goal), "is_success": success}

    @property
    def sim(self):
        """cdrb's own simulator under this env (after the first reset): what a cdrb controller is built on."""
        return self._sim

    def collides(self, states) -> np.ndarray:
        """Per state (..., obs_dim): inside an obstacle of the environment?"""
        states = _numbers(states, "states", "an array (..., obs_dim)")
        if states.ndim < 1 or states.shape[-1] != self.cdrb_spec.obs_dim:
            n = self.cdrb_spec.obs_dim
            raise BadInput(f"states of shape {states.shape}: finite states of {n} numbers expected",
                           hint="an array (..., obs_dim)")  # fmt: skip
        return np.asarray(self.family.in_collision(self.cdrb_spec, states))

    def render(self):
        raise BadInput("this env draws nothing", hint="`cdrb eval --video DIR` writes rollout GIFs")

    def close(self) -> None:
        if self._sim is not None:
            self._sim.close()
            self._sim = None


def _numbers(value, name: str, hint: str) -> np.ndarray:
    """``value`` as a float64 array of finite numbers, or a one-line BadInput naming ``name``."""
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise BadInput(f"{name} = {clip(repr(value), 40)}: not numbers", hint=hint) from None
    if not np.isfinite(array).all():
        raise BadInput(f"{name} of shape {array.shape}: a NaN or infinite number", hint=hint)
    return array


def register_envs() -> list[str]:
    """Register ``cdrb/<id>-v0`` for every stock environment id (again: a no-op); returns the gymnasium ids."""
    from cdrb_cli.envs.registry import FAMILIES

    ids = []
    for family in FAMILIES.entries():
        for env_id in family.env_ids():
            name = gym_id(env_id)
            if name not in gymnasium.registry:
                gymnasium.register(id=name, entry_point=CdrbEnv, kwargs={"env_id": env_id})
            ids.append(name)
    return ids


register_envs()
