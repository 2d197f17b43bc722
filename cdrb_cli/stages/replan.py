"""Closed-loop execution of a planner: ``cdrb eval --replan every:N|deviation:D [--repair-k K]``.

The paper plans once per episode. Here the episodes of an evaluation seed run in lockstep groups (one environment
and one controller each) and may be planned again during the episode:

* ``every:N`` plans again every N environment steps; ``deviation:D`` when the state is farther than D (in the
  obstacle dimensions, the positions that collide: the maze ball; Fetch's gripper and block) from where the
  current plan has it now (the controller's own clock, :meth:`~cdrb_cli.envs.family.Controller.progress`), at
  most once every ``min_gap`` steps;
* a new plan runs from the current state to the same goal, from scratch, or with ``repair_k`` as a *repair*: the
  previous plan's remainder (from where execution stands, padded with its last state to the horizon, its first
  state replaced by the current one) is degraded to step k and restored from there
  (:meth:`~cdrb_cli.methods.base.Planner.repair`: CDRB through the ball sampler, Diffuser by re-noising to
  timestep k, the MLP by re-predicting);
* all episodes of a group that are due plan in one batched sampler call; an episode that has reached its goal
  plans no more (its success is decided).

The first plan of every episode is the open-loop plan (the same sampler call and seed as ``--replan never``), so a
replanning interval longer than the episode reproduces open-loop evaluation exactly (tested). Per episode the eval
records the number of re-plans and the planning time of the whole episode; the plan measures (states in obstacles,
segments through them, the largest jump) cover every plan the episode made.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from cdrb_cli.configs import ReplanConfig
from cdrb_cli.envs.family import Controller, Env, EnvFamily, Episode, close_all
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.methods.base import Planner
from cdrb_cli.seeding import replan_rng
from cdrb_cli.stages.plan import replan_batch

#: episodes executed in lockstep (their re-plans share one batched sampler call)
GROUP = 25


@dataclass
class ClosedLoopEpisode:
    """What one closed-loop episode did: the states visited, and every plan with the env step it was made at."""

    states: np.ndarray
    goal: np.ndarray
    plans: list[np.ndarray] = field(default_factory=list)
    plan_steps: list[int] = field(default_factory=list)
    planning_seconds: float = 0.0

    @property
    def replans(self) -> int:
        return len(self.plans) - 1


def plan_at(plan: np.ndarray, s: float) -> np.ndarray:
    """The plan's state at plan time ``s`` (in planned states), linearly interpolated; clamped to the plan."""
    s = float(np.clip(s, 0, len(plan) - 1))
    i = int(np.floor(s))
    j = min(i + 1, len(plan) - 1)
    w = s - i
    return (1 - w) * plan[i] + w * plan[j]


def remainder(plan: np.ndarray, s: float, state: np.ndarray) -> np.ndarray:
    """The rest of ``plan`` from plan time ``s``: its states from floor(s) on, padded with the last one to the
    plan's length, the first state's observation part replaced by ``state`` (the current one)."""
    i = int(np.clip(np.floor(s), 0, len(plan) - 1))
    rest = plan[i:]
    out = np.concatenate([rest, np.repeat(rest[-1:], len(plan) - len(rest), axis=0)])
    out[0, : len(state)] = state
    return out


def deviation(spec: EnvSpec, plan: np.ndarray, s: float, state: np.ndarray) -> float:
    """Distance in the obstacle dimensions between ``state`` and the plan at plan time ``s``."""
    dims = spec.obstacles.dims
    return float(np.linalg.norm(state[dims] - plan_at(plan, s)[dims]))


def run_closed_loop(
    family: EnvFamily,
    spec: EnvSpec,
    method: Planner,
    episodes: list[Episode],
    first_plans: np.ndarray,
    make_controller: Callable[[Env], Controller],
    replan: ReplanConfig,
    steps: int,
    seeds: tuple[int, int, int],
    sampler=None,
    sample_steps=None,
    device="cpu",
    avoid=None,
    aims=None,
    envs: Sequence[Env] | None = None,
) -> list[ClosedLoopEpisode]:
    """Run ``episodes`` in lockstep from their open-loop plans ``first_plans`` (n, H, F), planning again as
    ``replan`` says; ``seeds`` = (the command's seed, the eval seed, the group index) seed every re-plan; ``aims``
    (states, goal states) -> the goal states re-plans aim at (waypoints toward far goals; None: the goals);
    ``envs``: at least one env per episode, reset here and left open (reused group after group); None: fresh
    ones, closed after."""
    n = len(episodes)
    stride = method.config.stride
    own = envs is None
    envs = [family.make_env(spec) for _ in episodes] if own else list(envs[:n])
    try:
        controllers = [make_controller(env) for env in envs]
        resets = [env.reset(ep) for env, ep in zip(envs, episodes)]
        obs = np.stack([r[0] for r in resets]).astype(np.float64)
        goals = np.stack([np.asarray(r[1], dtype=np.float64) for r in resets])
        goal_states = family.goal_state(spec, goals)
        runs = [
            ClosedLoopEpisode(states=np.empty(0), goal=goals[i], plans=[first_plans[i]], plan_steps=[0])
            for i in range(n)
        ]
        for c, p in zip(controllers, first_plans):
            c.reset(p)
        since = np.zeros(n, dtype=np.int64)  # env steps executed on the current plan
        done = np.zeros(n, dtype=bool)  # reached the goal: plans no more
        states = [obs]
        for t in range(steps):
            actions = [c.act(o, int(k)) for c, o, k in zip(controllers, obs, since)]
            obs = np.stack([env.step(a) for env, a in zip(envs, actions)]).astype(np.float64)
            states.append(obs)
            since += 1
            done |= family.success(spec, obs, goals)
            if t + 1 == steps:
                break
            due = _due(spec, replan, runs, controllers, obs, since, stride) & ~done
            if not due.any():
                continue
            idx = np.flatnonzero(due)
            previous = None
            if replan.repair_k is not None:
                previous = np.stack(
                    [remainder(runs[i].plans[-1], controllers[i].progress(int(since[i]), stride), obs[i]) for i in idx]
                )
            rng = replan_rng(seeds[0], seeds[1], seeds[2], t + 1)
            aim = goal_states[idx] if aims is None else aims(obs[idx], goal_states[idx])
            plans, seconds = replan_batch(
                method,
                obs[idx],
                aim,
                rng,
                sampler,
                replan.repair_steps if replan.repair_k is not None else sample_steps,
                previous,
                replan.repair_k,
                device,
                avoid,
            )
            for j, i in enumerate(idx):
                runs[i].plans.append(plans[j])
                runs[i].plan_steps.append(t + 1)
                runs[i].planning_seconds += seconds / len(idx)
                controllers[i].reset(plans[j])
                since[i] = 0
    finally:
        if own:
            close_all(envs)
    S = np.stack(states, axis=1)  # (n, steps + 1, obs_dim)
    for i, run in enumerate(runs):
        run.states = S[i]
    return runs


def _due(spec, replan: ReplanConfig, runs, controllers, obs, since, stride) -> np.ndarray:
    """Which episodes plan again after this step."""
    if replan.mode == "every":
        return since >= replan.every
    if replan.mode == "deviation":
        ready = since >= replan.min_gap
        return np.array(
            [
                bool(ready[i])
                and deviation(spec, runs[i].plans[-1], controllers[i].progress(int(since[i]), stride), obs[i])
                > replan.deviation
                for i in range(len(runs))
            ]
        )
    return np.zeros(len(runs), dtype=bool)
