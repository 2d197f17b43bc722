"""`cdrb eval`: plan once per episode, execute the plan with a controller in the simulator, and measure.

Protocol: for each evaluation seed, ``episodes`` start/goal pairs are drawn by the environment's family
(:meth:`~cdrb_cli.envs.family.EnvFamily.draw_episodes`), so every method sees the same pairs for the same seed.
Each episode: plan from the reset state to the goal state the family pins (for mazes: the goal at rest), execute
the plan for ``spec.episode_limit`` environment steps (the controller holds the goal after the plan ends), and
record an :class:`EpisodeResult`: success (the family's test, at any step), steps to success, final distance, the
fraction of planned states inside obstacles, whether the executed path touched one, path length until success
(and the family's default expert's on the same reset, for the normalized path length) and planning time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from cdrb_cli import artifacts, ui
from cdrb_cli.configs import EvalConfig, EvalSummary
from cdrb_cli.envs.family import Env, EnvFamily, Episode, close_all
from cdrb_cli.envs.geometry import largest_jump
from cdrb_cli.envs.registry import CONTROLLERS, EXPERTS, family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.seeding import EVAL_STREAMS, STREAM_EVAL, eval_plan_seed, step_rng
from cdrb_cli.stages.avoid import buffer_graph, mask_counts, prepare_planner, warn_unrouted
from cdrb_cli.stages.metrics import (
    failure_code,
)
from cdrb_cli.stages.plan import load_planner, sample_plans
from cdrb_cli.stages.plan_metrics import plan_measures
from cdrb_cli.stages.results import EpisodeResult, episode_arrays, failure_text, seed_result, summarize


@dataclass(frozen=True)
class Rollout:
    """One executed episode: the states visited and what they show."""

    states: np.ndarray
    success: bool
    steps: int
    final_distance: float
    collision: bool
    path_length: float
    execution_failure: str = ""  # a failed episode: why, had its plans been free (EnvFamily.execution_failure)


def run_episode(
    env: Env,
    spec: EnvSpec,
    episode: Episode,
    act: Callable[[np.ndarray, int], np.ndarray],
    steps: int,
    done: Callable[[], bool] | None = None,
) -> Rollout:
    """Execute ``act(state, t) -> action`` from the episode's seeded reset for ``steps`` steps, and measure;
    ``done``: the episode ends early once it says so after an action (an executor whose plan ran out)."""
    obs, goal = env.reset(episode)
    states = [obs]
    for t in range(steps):
        action = act(obs, t)
        if done is not None and done():
            break
        obs = env.step(action)
        states.append(obs)
    return measure(spec, np.array(states), goal, steps)


def measure(spec: EnvSpec, S: np.ndarray, goal: np.ndarray, steps: int) -> Rollout:
    """The record of the states ``S`` (steps + 1, obs_dim) one episode visited on its way to ``goal``."""
    family = family_of(spec)
    hits = np.flatnonzero(family.success(spec, S, goal))
    first = int(hits[0]) if hits.size else None
    collision = bool(family.in_collision(spec, S).any())
    return Rollout(
        states=S,
        success=first is not None,
        steps=first if first is not None else len(S) - 1,
        final_distance=float(family.distance(spec, S, goal)[-1]),
        collision=collision,
        path_length=family.path_length(spec, S if first is None else S[: first + 1]),
        execution_failure="" if first is not None else family.execution_failure(spec, S, collision),
    )


class ExpertReference:
    """The family's default expert, run on an episode's reset, for the normalized path length (0 when that
    expert cannot run without a file: the ratio is then not reported). Where the expert misses only for lack of
    time (``EnvFamily.expert_only_times_out``), the episodes it misses are pairs the limit is too short for (a
    scene or start protocol with longer routes than the map's timing), which cap every method (:meth:`warn`)."""

    def __init__(self, family: EnvFamily, spec: EnvSpec):
        self.name = family.experts[0]
        entry = EXPERTS.get(self.name)
        try:
            self.expert = entry.build(spec, entry.configure(None))
        except BadInput:
            self.expert = None
        self.spec = spec
        self.ran, self.missed, self.judged = 0, 0, family.expert_only_times_out

    def path_length(self, env: Env, episode: Episode) -> float:
        if self.expert is None:
            return 0.0
        obs, goal = env.reset(episode)
        self.expert.reset(obs, goal, np.random.default_rng(episode.seed))
        run = run_episode(env, self.spec, episode, lambda o, t: self.expert.act(o), self.spec.episode_limit)
        self.ran, self.missed = self.ran + 1, self.missed + (not run.success)
        return run.path_length

    def warn(self, extra_steps: int) -> None:
        """One line when the expert missed the goal in more than 1% of the episodes."""
        if not self.judged or not self.ran or self.missed <= 0.01 * self.ran:
            return
        given = f"; this eval gives the methods {extra_steps} more" if extra_steps else ""
        ui.warn(
            f"the {self.name} expert reaches the goal in only {self.ran - self.missed} of {self.ran} episodes within "
            f"the episode limit of {self.spec.episode_limit} env steps{given}: these pairs need more time than the "
            "limit gives (a scene or start protocol with longer routes), which caps every method's success (--set "
            "extra_steps=N runs each episode N steps longer)"
        )


#: episodes a policy runs in lockstep (one batched network call per step for all of them)
POLICY_BATCH = 25


def run_policy(
    family: EnvFamily,
    spec: EnvSpec,
    episodes: Sequence[Episode],
    policy,
    steps: int,
    rng: np.random.Generator,
    aims=None,
    envs: Sequence[Env] | None = None,
) -> tuple[list[Rollout], list[np.ndarray], float]:
    """Run a closed-loop policy on ``episodes`` in lockstep (one env each): every step, one call of
    ``policy.act`` for all of them. ``aims``: (function of states and goals giving the goals to act toward,
    env steps between two calls of it), toward waypoints; None: the episodes' goals throughout. ``envs``: at
    least one env per episode, reset here and left open (an eval reuses them batch after batch, as its open-loop
    path reuses one env: building a MuJoCo env costs about 0.1 s); None: fresh ones, closed after. Returns the
    rollouts, the goals and the mean seconds per ``act`` call."""
    own = envs is None
    envs = [family.make_env(spec) for _ in episodes] if own else list(envs[: len(episodes)])
    try:
        resets = [env.reset(ep) for env, ep in zip(envs, episodes)]
        obs = np.stack([r[0] for r in resets])
        goals = np.stack([np.asarray(r[1], dtype=np.float64) for r in resets])
        states = [obs]
        policy.reset(len(episodes), rng)
        seconds, toward = 0.0, goals
        for t in range(steps):
            t0 = time.perf_counter()
            if aims is not None and t % aims[1] == 0:
                toward = aims[0](obs, goals)
            actions = policy.act(obs, toward, rng)
            seconds += time.perf_counter() - t0
            obs = np.stack([env.step(a) for env, a in zip(envs, actions)])
            states.append(obs)
    finally:
        if own:
            close_all(envs)
    S = np.stack(states, axis=1)  # (episodes, steps + 1, obs_dim)
    return [measure(spec, S[i], goals[i], steps) for i in range(len(episodes))], list(goals), seconds / max(steps, 1)


def evaluate(
    model,
    config: EvalConfig,
    out,
    device="cpu",
    keep_plans: bool = True,
    video_dir=None,
    videos: int = 0,
    replan_plot=None,
    spec: EnvSpec | None = None,
    route_buffer=None,
):
    """Evaluate a model (a planner open or closed loop, or a policy) and write the eval artifact ``out``;
    ``replan_plot``: a picture of the first closed-loop episode's successive plans over its executed path;
    ``spec``: the spec evaluated in (the model's under ``config.protocol`` when None; a caller with
    ``config.scene`` passes the spec of that map); ``route_buffer``: the buffer artifact of
    ``config.avoid.route_buffer`` (a parent of the eval)."""
    t0 = time.time()
    family = family_of(model.manifest.env)
    if spec is None:
        if config.scene is not None:
            raise ValueError("config.scene is set: pass the spec of its map (stages.plan.scene_spec)")
        spec = family.protocol_spec(model.manifest.env, config.protocol)
    if METHODS.get(model.manifest.config.method.name).kind == "policy":
        return evaluate_policy(model, config, out, spec, device, video_dir, videos, route_buffer)
    method = load_planner(model, device=device, ema=config.use_ema)
    avoid = prepare_planner(method, spec, config.avoid, route_buffer)
    aims = _waypoints(method, spec, config, avoid, route_buffer, model.path)
    if spec.pin_end_dims != model.manifest.env.pin_end_dims:  # a protocol that pins more (the official Fetch pin)
        method.pinned_end = spec.pin_end_dims
    METHODS.get(method.name).check_sampler(config.sampler)
    env = family.make_env(spec)
    pool: list[Env] = []  # closed loop: one env per episode of a lockstep group
    controller = CONTROLLERS.get(config.controller.name).build(
        spec, env, config.controller, model.manifest.config.stride
    )
    expert = ExpertReference(family, spec)
    steps = spec.episode_limit + config.extra_steps
    step_limit = family.plan_step_limit(spec, model.manifest.config.stride) or 0.0
    results: list[EpisodeResult] = []
    all_plans, per_seed, executed, drawn = [], [], [], []
    with ui.progress() as bar:
        task = bar.add_task(f"eval {method.name}", total=len(config.seeds) * config.episodes, info="")
        for seed in config.seeds:
            episodes = family.draw_protocol_episodes(
                spec, config.episodes, seed, EVAL_STREAMS[config.stream], config.protocol
            )
            starts, goals = family.reset_states(spec, episodes, env)
            goal_states = family.goal_state(spec, goals)
            plans, _, _, _, sec_batch = sample_plans(
                method,
                starts,
                goal_states if aims is None else aims(starts, goal_states),
                1,
                eval_plan_seed(config.seed, seed),
                config.sampler,
                config.sample_steps,
                batch_size=max(1, config.episodes),
                device=device,
                avoid=avoid,
            )
            sec_plan = sec_batch / len(plans)
            ctx = _SeedRun(family, spec, seed, episodes, plans, env, expert, sec_plan, steps, step_limit)
            if config.replan.mode == "never":
                runs = _open_loop(ctx, starts, goals, controller)
            else:
                runs = _closed_loop(ctx, method, config, pool, avoid, aims)
            for plan, states_visited, result, history in runs:
                results.append(result)
                if len(executed) < videos:
                    executed.append((plan, states_visited, result.goal, result.success))
                if replan_plot is not None and history is not None and not drawn:
                    drawn.append((history, states_visited, result.goal))
                bar.update(task, advance=1, info=f"success {np.mean([r.success for r in results]):.1%}")
            all_plans.append(plans)
            per_seed.append(seed_result(seed, [r for r in results if r.seed == seed]))
    close_all([env, *pool])
    warn_unrouted(avoid)
    expert.warn(config.extra_steps)
    arrays = episode_arrays(results)
    plans = np.concatenate(all_plans).astype(np.float32)
    arrays.update(plan_measures(spec, plans))  # what report takes from the plans, kept without them too
    if keep_plans:
        arrays["plans"] = plans
    summary = _summary(method.name, model, per_seed, t0)
    summary = summary.model_copy(update={"masked": mask_counts(method, avoid), "variant": method.variant()})
    parents = [model] if route_buffer is None else [model, route_buffer]
    manifest = artifacts.make_manifest(
        "eval", env=spec, config=config, seed=config.seed, parents=parents, summary=summary
    )
    artifacts.save(out, "eval", manifest, arrays)
    if video_dir is not None and executed:
        from cdrb_cli.envs.render import rollout_gifs

        rollout_gifs(spec, executed, video_dir, label=method.name)
    if replan_plot is not None and drawn:
        from cdrb_cli.envs.render import plot_replans

        (made, made_at), visited, goal = drawn[0]
        plot_replans(spec, made, made_at, visited, goal, replan_plot, method.name, config.replan)
    return artifacts.load(out, "eval")


def _waypoints(method, spec: EnvSpec, config: EvalConfig, avoid, route_buffer=None, path=None):
    """With ``replan.waypoint_reach``, the function that turns each plan's goal into its waypoint
    (:func:`~cdrb_cli.stages.routes.waypoint_aims`) along the routes ``replan.waypoint_graph`` names through the
    buffer ``route_buffer`` (``avoid.route_buffer``) or the model's own: its transition graph, or its states joined
    by free steps (the avoidance's graph where it has one); None without it."""
    from cdrb_cli.stages.avoid import route_states
    from cdrb_cli.stages.routes import TransitionRoutes, waypoint_aims

    replan = config.replan
    if replan.waypoint_reach is None:
        return None
    if route_buffer is None and not hasattr(method, "points"):
        raise _no_route_buffer(method.name)
    if replan.waypoint_graph == "free-steps":
        graph = avoid.graph if avoid.graph is not None else buffer_graph(method, spec, config.avoid, route_buffer)
    elif route_buffer is not None:
        graph = TransitionRoutes(spec, route_states(method, spec, route_buffer), route_buffer.graph()[0])
    elif method.buffer_graph is None:
        raise BadInput(
            f"replan.waypoint_graph = transitions: {path or 'the model'} carries no transition graph (models "
            "trained from a buffer with one carry it)",
            hint='retrain it from a buffer of `cdrb cluster`, or set replan.waypoint_graph="free-steps"',
        )
    else:  # the model's own buffer, unmasked: the graph's indices are into all of it
        states = method.normalizer.unnormalize(np.asarray(method.points, dtype=np.float64))
        graph = TransitionRoutes(spec, states, method.buffer_graph[0])
    return waypoint_aims(graph, spec, replan.waypoint_reach, method.feature_dim)


@dataclass(frozen=True)
class _SeedRun:
    """What executing the episodes of one eval seed needs, open or closed loop."""

    family: EnvFamily
    spec: EnvSpec
    seed: int
    episodes: list[Episode]
    plans: np.ndarray  # the open-loop plans (episodes, H, F)
    env: Env  # for the expert's reference path
    expert: ExpertReference
    sec_plan: float  # seconds per open-loop plan
    steps: int
    step_limit: float


def _open_loop(ctx: _SeedRun, starts, goals, controller):
    """Yield (plan, states, result, None) for every episode of one eval seed: one plan each, executed by
    ``controller``."""
    spec = ctx.spec
    states = ctx.plans[..., : spec.obs_dim]
    in_wall = ctx.family.in_collision(spec, states)
    crosses = ctx.family.path_in_collision(spec, states)
    goal_crosses = ctx.family.goal_path_in_collision(spec, states)
    jumps = largest_jump(states, spec.obstacles.dims)
    for e, episode in enumerate(ctx.episodes):
        controller.reset(ctx.plans[e])
        run = run_episode(ctx.env, spec, episode, controller.act, ctx.steps, lambda: controller.finished)
        result = _result(
            ctx.seed,
            episode,
            run,
            ctx.expert.path_length(ctx.env, episode),
            ctx.sec_plan,
            starts[e],
            goals[e],
            plan_failed=bool(goal_crosses[e]),
            plan_in_wall_fraction=float(in_wall[e].mean()),
            plan_crosses_obstacle=bool(crosses[e]),
            plan_max_jump=float(jumps[e]),
            plan_step_limit=ctx.step_limit,
        )
        yield ctx.plans[e], run.states, result, None


def _closed_loop(ctx: _SeedRun, method, config: EvalConfig, envs: list[Env], avoid=None, aims=None):
    """Yield (last plan, states, result, (plans, steps they were made at)) for every episode of one eval seed
    executed closed loop (stages/replan.py) in lockstep groups; the plan measures cover every plan an episode
    made; ``envs``: the eval's envs for a group, grown here to the largest group and reused (the caller closes
    them); ``aims``: where each re-plan aims (:func:`_waypoints`)."""
    from cdrb_cli.stages.replan import GROUP, run_closed_loop

    spec, family = ctx.spec, ctx.family
    entry = CONTROLLERS.get(config.controller.name)
    stride = method.config.stride
    for g, b in enumerate(range(0, len(ctx.episodes), GROUP)):
        group = ctx.episodes[b : b + GROUP]
        envs.extend(family.make_env(spec) for _ in range(len(group) - len(envs)))
        runs = run_closed_loop(
            family,
            spec,
            method,
            group,
            ctx.plans[b : b + GROUP],
            lambda e: entry.build(spec, e, config.controller, stride),
            config.replan,
            ctx.steps,
            (config.seed, ctx.seed, g),
            config.sampler,
            config.sample_steps,
            method.device,
            avoid,
            aims,
            envs,
        )
        for episode, run in zip(group, runs):
            made = np.stack(run.plans)[..., : spec.obs_dim]  # (plans, H, obs_dim)
            total = ctx.sec_plan + run.planning_seconds
            result = _result(
                ctx.seed,
                episode,
                measure(spec, run.states, run.goal, ctx.steps),
                ctx.expert.path_length(ctx.env, episode),
                total / len(run.plans),
                run.states[0],
                run.goal,
                plan_failed=bool(family.goal_path_in_collision(spec, made).any()),
                plan_in_wall_fraction=float(family.in_collision(spec, made).mean()),
                plan_crosses_obstacle=bool(family.path_in_collision(spec, made).any()),
                plan_max_jump=float(largest_jump(made, spec.obstacles.dims).max()),
                plan_step_limit=ctx.step_limit,
                replans=run.replans,
                planning_seconds=total,
            )
            yield run.plans[-1], run.states, result, (run.plans, run.plan_steps)


def evaluate_policy(
    model, config: EvalConfig, out, spec: EnvSpec, device="cpu", video_dir=None, videos: int = 0, route_buffer=None
):
    """`cdrb eval` of a closed-loop policy: the same pairs, episode limit and measures as for a planner; the plan
    measures are "not measured" (NaN, reported as n/a) and ``plan_seconds`` is the time of one ``act`` call (one
    batched network call for up to :data:`POLICY_BATCH` episodes, divided by their number). With
    ``replan.waypoint_reach`` the policy acts toward waypoints along routes through ``route_buffer``, given anew
    every ``replan.every`` env steps (the means a planner gets toward far goals)."""
    from cdrb_cli.methods.checkpoint import load_method

    t0 = time.time()
    family = family_of(spec)
    policy = load_method(model, device=device, ema=config.use_ema)
    METHODS.get(policy.name).check_sampler(config.sampler)
    policy.config = policy.config.model_copy(
        update={"method": policy.config.method.model_copy(update={"sampler": config.sampler})}
    )
    aims = _policy_waypoints(model, spec, config, route_buffer)
    env = family.make_env(spec)
    pool = [family.make_env(spec) for _ in range(min(POLICY_BATCH, config.episodes))]
    expert = ExpertReference(family, spec)
    steps = spec.episode_limit + config.extra_steps
    results: list[EpisodeResult] = []
    per_seed, executed = [], []
    with ui.progress() as bar:
        task = bar.add_task(f"eval {policy.name}", total=len(config.seeds) * config.episodes, info="")
        for seed in config.seeds:
            episodes = family.draw_protocol_episodes(
                spec, config.episodes, seed, EVAL_STREAMS[config.stream], config.protocol
            )
            rng = step_rng(config.seed, STREAM_EVAL, seed)
            for b in range(0, len(episodes), POLICY_BATCH):
                batch = episodes[b : b + POLICY_BATCH]
                runs, goals, sec = run_policy(family, spec, batch, policy, steps, rng, aims, pool)
                for episode, run, goal in zip(batch, runs, goals):
                    length = expert.path_length(env, episode)
                    per_call = sec / len(batch)
                    results.append(
                        _result(
                            seed, episode, run, length, per_call, run.states[0], goal, planning_seconds=per_call * steps
                        )
                    )
                    if len(executed) < videos:
                        executed.append((run.states, run.states, goal, run.success))
                bar.update(task, advance=len(batch), info=f"success {np.mean([r.success for r in results]):.1%}")
            per_seed.append(seed_result(seed, [r for r in results if r.seed == seed], policy=True))
    close_all([env, *pool])
    expert.warn(config.extra_steps)
    summary = _summary(policy.name, model, per_seed, t0).model_copy(update={"variant": policy.variant()})
    parents = [model] if route_buffer is None else [model, route_buffer]
    manifest = artifacts.make_manifest(
        "eval", env=spec, config=config, seed=config.seed, parents=parents, summary=summary
    )
    artifacts.save(out, "eval", manifest, episode_arrays(results, plans=False))
    if video_dir is not None and executed:
        from cdrb_cli.envs.render import rollout_gifs

        rollout_gifs(spec, executed, video_dir, label=policy.name)
    return artifacts.load(out, "eval")


def _summary(name: str, model, per_seed, t0: float) -> EvalSummary:
    """The eval's summary: the per-seed results pooled, and what tells the model evaluated apart."""
    preset, seconds = model.manifest.config.preset, round(time.time() - t0, 3)
    return summarize(name, preset, per_seed, seconds, trained_steps(model), training_digest(model))


def trained_steps(model) -> int:
    """The training steps of the model evaluated: its config's (a snapshot's is its step), or the step an
    unfinished training stopped at."""
    st = model.manifest.state
    return model.manifest.config.steps if st.finished else int(st.step)


#: training settings that do not change what a model learns, beside its config's ``bookkeeping``: left out of
#: :func:`training_digest` (the step count is ``model_steps``'s)
NOT_TRAINING = ("seed", "steps", "checkpoint_every")


def training_digest(model) -> str:
    """sha256 of the model's training settings less its seed and bookkeeping: equal for the seeds of one method."""
    import hashlib
    import json

    config = model.manifest.config
    left_out = {*NOT_TRAINING, *config.bookkeeping}
    kept = {k: v for k, v in config.model_dump(mode="json").items() if k not in left_out}
    return hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()


def _no_route_buffer(name: str) -> BadInput:
    """The one-line refusal of waypoints for a model that carries no buffer and was given no route buffer."""
    return BadInput(
        f"replan.waypoint_reach: routes go through a replay buffer, and a {name} model carries none",
        hint="name one: --set avoid.route_buffer=BUFFER.h5 (the buffer of the model's demos)",
    )


def _policy_waypoints(model, spec: EnvSpec, config: EvalConfig, route_buffer=None):
    """With ``replan.waypoint_reach``, (the function giving a policy's waypoint goals, env steps between two of them)
    along the routes ``replan.waypoint_graph`` names through ``route_buffer`` (a policy keeps no buffer); None
    without it."""
    from cdrb_cli.stages.avoid import buffer_states
    from cdrb_cli.stages.routes import BufferGraph, TransitionRoutes, waypoint_goals

    replan, name = config.replan, model.manifest.config.method.name
    if replan.waypoint_reach is None:
        return None
    if replan.mode != "every":
        raise BadInput(
            f"replan.mode = {replan.mode}: a {name} policy is given its next waypoint on a clock",
            hint="set replan.mode=every and replan.every=STEPS",
        )
    if route_buffer is None:
        raise _no_route_buffer(name)
    states = buffer_states(route_buffer, spec, model.manifest.env.id)
    if replan.waypoint_graph == "free-steps":
        graph = BufferGraph(spec, states, clearance=config.avoid.route_clearance)
    else:
        graph = TransitionRoutes(spec, states, route_buffer.graph()[0])
    return waypoint_goals(graph, spec, replan.waypoint_reach), replan.every


def _result(
    seed, episode, run: Rollout, expert_length, seconds, start, goal, plan_failed: bool = False, **plan
) -> EpisodeResult:
    """One episode's record; ``plan_failed``: a plan's path of the goal object crossed an obstacle (the failure's
    cause "plan" comes first); ``plan``: the plan measures (a policy has none: NaN, never written), the number of
    re-plans and the episode's whole planning time."""
    nan = float("nan")
    unplanned = dict(
        plan_in_wall_fraction=nan,
        plan_crosses_obstacle=False,
        plan_max_jump=nan,
        plan_step_limit=nan,
        replans=0,
        planning_seconds=seconds,
    )
    merged = {**unplanned, **plan}
    return EpisodeResult(
        seed=seed,
        episode_seed=episode.seed,
        success=run.success,
        steps=run.steps,
        final_distance=run.final_distance,
        executed_collision=run.collision,
        path_length=run.path_length,
        expert_path_length=expert_length,
        plan_seconds=seconds,
        start=start,
        goal=goal,
        failure=failure_code(run.success, plan_failed, run.execution_failure),
        **merged,
    )


def summary_line(s: EvalSummary, config: EvalConfig, env_id: str) -> str:
    """One line of what an eval measured, for logs: success over seeds and episodes, planned and executed
    collisions, planning time (per episode when re-planning), failures by cause."""
    crossing = "" if s.plan_crossing_mean is None else f"; plans through obstacles {100 * s.plan_crossing_mean:.1f}%"
    planner = s.in_wall_mean is not None
    text = (
        f"{s.method} on {ui.plain(env_id)} ({config.stream} pairs): success {100 * s.success_mean:.1f} ± "
        f"{100 * s.success_std:.1f}% over {len(config.seeds)} seeds x {config.episodes} episodes; "
    )
    if planner:
        text += f"planned states in obstacles {100 * s.in_wall_mean:.2f}%{crossing}; "
    else:
        text += "closed loop (no plans); "
    text += f"executed collisions {100 * s.executed_collision_mean:.1f}%; "
    if planner:
        text += f"plan {1000 * s.plan_seconds_mean:.1f} ms"
    else:
        text += f"{1000 * s.plan_seconds_mean:.2f} ms per episode step"
    if config.replan.mode != "never" and s.replans_mean is not None:
        text += (
            f" ({s.replans_mean:.1f} re-plans, {1000 * s.planning_seconds_mean:.0f} ms planning per episode: "
            f"{config.replan.label()})"
        )
    if s.failures and any(s.failures.values()):
        text += f"; failed episodes by cause: {failure_text(s.failures)}"
    return text


def eval_artifact(
    model, config: EvalConfig, out, *, force: bool, device, scene: EnvSpec, route_buffer=None, flag="--out", **kw
):
    """The eval artifact of ``config`` at ``out``, evaluated in ``scene`` under the config's protocol, unless the
    file there is already up to date (same config and parents); ``kw``: :func:`evaluate`'s outputs (plans, videos,
    the re-planning picture); ``flag``: how errors name ``out``. What `cdrb eval` and the Python API both run."""
    spec = family_of(model.manifest.env).protocol_spec(scene, config.protocol)
    return artifacts.produce(
        out,
        "eval",
        force,
        config,
        lambda: evaluate(model, config, out, device=device, spec=spec, route_buffer=route_buffer, **kw),
        parents=[model] if route_buffer is None else [model, route_buffer],
        env=spec,
        flag=flag,
    )
