"""Every stock cdrb environment as a gymnasium env: ``import cdrb_cli.gym`` registers ``cdrb/<id>-v0`` for each id
`cdrb envs` lists (the mazes, the Fetch tasks with and without walls; ``cdrb/<id>`` for OGBench's ids, which end in
their own version), so ``gymnasium.make("cdrb/maze-tight-v0")``
works in any gymnasium loop (or, without the import, ``gymnasium.make("cdrb_cli.gym:cdrb/maze-tight-v0")``).

The env is cdrb's own simulator for the id (the same MuJoCo model, dynamics and reset noise as `cdrb eval`):
observations are cdrb's raw state vectors, actions the family's, the reward 1 on success (within the id's success
radius) and 0 otherwise, and an episode terminates on success and is truncated at the id's episode limit. A reset
draws its start and goal from the environment's evaluation protocol (``options={"episode": EPISODE}`` resets to a
given :class:`~cdrb_cli.envs.family.Episode`, e.g. one of `cdrb eval`'s pairs); ``info["goal"]`` is the goal.
``env.unwrapped.cdrb_spec`` is the environment's spec (its scene and obstacles) and ``env.unwrapped.collides(states)``
its collision test."""

from __future__ import annotations

import re

import gymnasium
import numpy as np
from gymnasium import spaces

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

    def __init__(self, env_id: str, protocol: str | None = None, stream: str = "test"):
        from cdrb_cli.envs.registry import family_of, make_spec
        from cdrb_cli.seeding import EVAL_STREAMS

        self.cdrb_spec = make_spec(env_id)
        self.family = family_of(self.cdrb_spec)
        self.protocol = protocol or self.family.protocol
        self._stream = EVAL_STREAMS[stream]
        spec = self.cdrb_spec
        self.observation_space = spaces.Box(-np.inf, np.inf, (spec.obs_dim,), np.float64)
        self.action_space = spaces.Box(-1.0, 1.0, (spec.action_dim,), np.float64)
        self._sim = None
        self.goal = np.zeros(spec.goal_dim)
        self._steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        episode = (options or {}).get("episode")
        if episode is None:
            draw = int(self.np_random.integers(2**31)) if seed is None else int(seed)
            episode = self.family.draw_protocol_episodes(self.cdrb_spec, 1, draw, self._stream, self.protocol)[0]
        if self._sim is None:
            self._sim = self.family.make_env(self.cdrb_spec)
        state, self.goal = self._sim.reset(episode)
        self._steps = 0
        return np.asarray(state, np.float64), {"goal": np.array(self.goal), "episode": episode}

    def step(self, action):
        state = np.asarray(self._sim.step(np.asarray(action, np.float64)), np.float64)
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
        return np.asarray(self.family.in_collision(self.cdrb_spec, np.asarray(states, np.float64)))

    def close(self) -> None:
        if self._sim is not None:
            self._sim.close()
            self._sim = None


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
