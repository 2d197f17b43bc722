"""`cdrb collect`: roll out an expert and write a `demos` artifact."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts, ui
from cdrb_cli.configs import CollectConfig, CollectSummary
from cdrb_cli.envs.family import Env, Episode, Expert
from cdrb_cli.envs.registry import EXPERTS, family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.seeding import STREAM_COLLECT
from cdrb_cli.settings import Setting, apply, validate
from cdrb_cli.workers import die_with_parent, sigint_ignored


def rollout(env: Env, expert: Expert, spec: EnvSpec, episode: Episode, limit: int):
    """One episode: returns (states (T+1, obs), actions (T+1, act) with a zero last row, goal, success)."""
    family = family_of(spec)
    rng = np.random.default_rng(episode.seed)
    obs, goal = env.reset(episode)
    expert.reset(obs, goal, rng)
    states, actions = [obs], []
    success = bool(family.success(spec, obs, goal))
    for _ in range(limit):
        a = expert.act(obs)
        obs = env.step(a)
        actions.append(a)
        states.append(obs)
        success = success or bool(family.success(spec, obs, goal))
        if expert.settled(obs, goal):
            break
    actions.append(np.zeros(spec.action_dim))
    return np.array(states), np.array(actions), goal, bool(success)


def collect_config(
    spec: EnvSpec,
    episodes: int,
    seed: int = 0,
    expert: str | None = None,
    policy: Path | None = None,
    valid_fraction: float | None = None,
    settings: Sequence[Setting] = (),
    starts: str = "protocol",
) -> CollectConfig:
    """The config of ``cdrb collect``: ``expert`` is one of the family's experts (default: its first), with
    ``settings`` on its fields (``--set expert.routes='["over"]'``)."""
    family = family_of(spec)
    name = expert or family.experts[0]
    if name not in family.experts:
        raise BadInput(
            f"--expert {name!r}: not an expert of the {family.name} environments",
            hint=f"use {', '.join(family.experts)}",
        )
    for s in settings:
        if s.path[0] != "expert" or s.path in (("expert",), ("expert", "kind")):
            raise BadInput(
                f"{s.source}: `cdrb collect --set` sets expert.<field>",
                hint="the expert, episodes, split and seed have their own flags; `cdrb config collect` lists the "
                "experts' fields",
            )
    expert_cfg = EXPERTS.get(name, "--expert").configure(policy)
    for s in settings:
        if len(s.path) > 1 and s.path[1] in type(expert_cfg).flag_fields:
            raise BadInput(
                f"{s.source}: expert.{s.path[1]} comes from --policy (the file and its sha256)",
                hint="pass the policy with --policy PATH",
            )
    parts = starts.split("+")
    if any(p != "protocol" and p not in family.start_protocols for p in parts) or len(set(parts)) != len(parts):
        choices = ", ".join(["protocol", *family.start_protocols])
        raise BadInput(
            f"--starts {starts!r}: not a start distribution of the {family.name} environments",
            hint=f"use {choices}, or several joined by + (episodes alternate between them)",
        )
    if valid_fraction is not None:  # as a setting, so a value the config refuses is said with the flag's name
        settings = [Setting(("valid_fraction",), valid_fraction, f"--valid-fraction {valid_fraction}"), *settings]
    base = {"env": spec.id, "episodes": episodes, "expert": expert_cfg.model_dump(mode="json"), "seed": seed}
    if starts != "protocol":  # recorded only when it differs, so the demos of the default stay what they were
        base["starts"] = starts
    config = validate(CollectConfig, apply(base, settings), settings, "collect")
    check_split(config.episodes, config.valid_fraction)
    return config


def held_out(episodes: int, valid_fraction: float) -> int:
    """How many of ``episodes`` the split holds out for validation."""
    return int(round(valid_fraction * episodes))


def check_split(episodes: int, valid_fraction: float) -> None:
    """Refuse a split that leaves no training episode (training and the buffer's normalizer read only those)."""
    if held_out(episodes, valid_fraction) >= episodes:
        raise BadInput(
            f"--valid-fraction {valid_fraction}: holds out all {episodes} episodes, none is left to train on",
            hint="collect more episodes or pass a smaller --valid-fraction",
        )


def draw_starts(family, spec: EnvSpec, episodes: int, seed: int, starts: str) -> list[Episode]:
    """The episodes of a collect: drawn by the protocol, or by another start distribution of the family, or (``A+B``)
    alternately by each of several (episode i by distribution i mod n, each with its own draws)."""
    parts = starts.split("+")
    draws = [
        family.draw_protocol_episodes(spec, episodes, seed, STREAM_COLLECT, None if p == "protocol" else p)
        for p in parts
    ]
    return [draws[i % len(parts)][i] for i in range(episodes)]


_WORKER_ENVS: dict[str, tuple] = {}  # a pool worker keeps one env and expert per (spec, config)


def _rollouts(spec: EnvSpec, config: CollectConfig, plan: list[Episode], limit: int) -> list[tuple]:
    """In a pool worker: roll out ``plan``'s episodes: [(states, actions, goal, success), ...]. Every episode is
    seeded by its own seed and reset from its own draw, so the result does not depend on which process ran it."""
    key = spec.model_dump_json() + config.model_dump_json()
    if key not in _WORKER_ENVS:
        _WORKER_ENVS[key] = _env_and_expert(spec, config)
    env, agent = _WORKER_ENVS[key]
    return [rollout(env, agent, spec, episode, limit) for episode in plan]


def limit_spec(spec: EnvSpec, starts: str) -> EnvSpec:
    """``spec`` with the longest episode limit its start distributions' protocols give (a start anywhere in a map
    may need longer than one from its start cells)."""
    family = family_of(spec)
    limit = max([spec.episode_limit] + [family.protocol_spec(spec, p).episode_limit for p in starts.split("+")])
    return spec if limit <= spec.episode_limit else spec.model_copy(update={"episode_limit": limit})


def _env_and_expert(spec: EnvSpec, config: CollectConfig) -> tuple[Env, Expert]:
    return family_of(spec).make_env(spec), EXPERTS.get(config.expert.kind).build(spec, config.expert)


def _worker_init(parent: int | None = None) -> None:
    """A rollout worker's start: one torch thread (the pool is the parallelism), and the kernel's promise to end
    it when its parent dies (:func:`cdrb_cli.workers.die_with_parent`)."""
    os.environ["OMP_NUM_THREADS"] = "1"  # before torch is imported there
    die_with_parent(parent)


def collect_workers(episodes: int, workers: int | None) -> int:
    """Processes for a collect: ``workers`` when given, else one per CPU core (up to 8) with at least 100 episodes
    each (starting a process costs ~2 s of imports, more than 100 maze episodes take)."""
    if workers is not None:
        return max(1, min(workers, episodes))
    return max(1, min(os.cpu_count() or 1, 8, episodes // 100))


def collect(spec: EnvSpec, config: CollectConfig, out: Path, workers: int | None = 1) -> artifacts.Demos:
    """Roll out the configured expert for ``config.episodes`` episodes and write the demos artifact to ``out``.

    ``workers`` > 1 rolls episodes out in that many processes (None: `collect_workers`'s choice); the demos are
    the same array for array whatever the number (each episode has its own seed and reset; tested)."""
    t0 = time.time()
    seed, episodes = config.seed, config.episodes
    family = family_of(spec)
    plan = draw_starts(family, spec, episodes, seed, config.starts)
    chunk = 20  # episodes per task: small enough for a live progress bar, large enough to amortise the hand-off
    parts = [plan[i : i + chunk] for i in range(0, episodes, chunk)]
    n_workers = min(collect_workers(episodes, workers), len(parts))  # a worker without a part would only start up
    all_states, all_actions, all_goals, success = [], [], [], []
    routes: dict[str, dict[str, int]] = {}
    with ui.progress() as bar:
        task = bar.add_task(ui.plain(f"collect {spec.id}", 60), total=episodes, info="")
        pool = env = None
        limit = family.collect_limit(limit_spec(spec, config.starts))
        if n_workers == 1:
            env, agent = _env_and_expert(spec, config)
            results = ([rollout(env, agent, spec, ep, limit) for ep in part] for part in parts)
        else:
            with sigint_ignored():  # the workers never take Ctrl-C: this process stops them after their part
                pool = ProcessPoolExecutor(
                    n_workers, mp_context=get_context("spawn"), initializer=_worker_init, initargs=(os.getpid(),)
                )
                results = pool.map(_rollouts, [spec] * len(parts), [config] * len(parts), parts, [limit] * len(parts))
        try:
            for part in results:
                for S, A, goal, ok in part:
                    all_states.append(S)
                    all_actions.append(A)
                    all_goals.append(np.repeat(goal[None], len(S), axis=0))
                    success.append(ok)
                    route = family.route(spec, S, goal)
                    if route is not None:
                        group, label = route
                        routes.setdefault(group, {})
                        routes[group][label] = routes[group].get(label, 0) + 1
                bar.update(task, completed=len(success), info=f"success {np.mean(success):.1%}")
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
            if env is not None:
                env.close()
    seeds = [ep.seed for ep in plan]
    return write_demos(out, spec, config, all_states, all_actions, all_goals, seeds, success, routes, t0)


def route_shares(routes: dict[str, dict[str, int]]) -> str:
    """The share of each route label over all episodes (``over 48%, around x- 27%, ...``), most common first."""
    totals: dict[str, int] = {}
    for group in routes.values():
        for label, n in group.items():
            totals[label] = totals.get(label, 0) + n
    n = max(sum(totals.values()), 1)
    return ", ".join(f"{label} {100 * c / n:.0f}%" for label, c in sorted(totals.items(), key=lambda kv: -kv[1]))


def write_demos(
    out: Path, spec: EnvSpec, config: CollectConfig, states, actions, goals, seeds, success, routes, t0, source=None
):
    """Write per-episode lists (states (T+1, obs), actions (T+1, act) with a zero last row, goals (T+1, goal), reset
    seeds, success) as a demos artifact: flat step arrays, the episode index, the train/valid split drawn from
    ``config.seed`` and the summary. Shared by collection and by imports (``source``: the dataset imported, named
    when its data are what a demos file may not hold; nothing is written then)."""
    seed, episodes = config.seed, len(states)
    lengths_arr = np.array([len(S) for S in states], dtype=np.int64)
    observations = np.concatenate(states).astype(np.float32)
    check_split(episodes, config.valid_fraction)
    split_rng = np.random.default_rng([seed, STREAM_COLLECT, 99])
    valid = np.zeros(episodes, dtype=bool)
    valid[split_rng.permutation(episodes)[: held_out(episodes, config.valid_fraction)]] = True
    summary = CollectSummary(
        episodes=episodes,
        steps=int(lengths_arr.sum()),
        success_rate=float(np.mean(success)),
        mean_length=float(lengths_arr.mean()),
        max_length=int(lengths_arr.max()),
        states_in_walls=int(family_of(spec).in_collision(spec, observations).sum()),
        train_episodes=int((~valid).sum()),
        valid_episodes=int(valid.sum()),
        routes={k: dict(sorted(v.items())) for k, v in sorted(routes.items())},
        wall_time_s=round(time.time() - t0, 3),
    )
    manifest = artifacts.make_manifest("demos", env=spec, config=config, seed=seed, summary=summary)
    arrays = {
        "steps/observations": observations,
        "steps/actions": np.concatenate(actions).astype(np.float32),
        "steps/desired_goals": np.concatenate(goals).astype(np.float32),
        "episodes/start": np.concatenate([[0], np.cumsum(lengths_arr)[:-1]]).astype(np.int64),
        "episodes/length": lengths_arr,
        "episodes/seed": np.array(seeds, dtype=np.int64),
        "episodes/success": np.array(success, dtype=bool),
        "episodes/valid": valid,
    }
    problem = artifacts.Demos.check_data(manifest, arrays)  # what the reader would refuse is never written
    if problem is not None:
        raise BadInput(
            f"{source or f'collect {spec.id}'}: {problem}",
            hint=f"is {spec.id} the dataset's environment? (--env)" if source else "check the expert (--policy)",
        )
    artifacts.save(out, "demos", manifest, arrays)
    return artifacts.load(out, "demos")


def check_workers(workers: int | None) -> None:
    """Refuse more collection workers than twice the machine's cores (each holds an environment, ~120 MB)."""
    import os

    cores = os.cpu_count() or 1
    if workers is not None and workers > 2 * cores:
        raise BadInput(
            f"--workers {workers}: more than twice this machine's {cores} cores (each worker holds an environment "
            "and about 120 MB)",
            hint=f"use at most {2 * cores}, or leave --workers out (one per core)",
        )
