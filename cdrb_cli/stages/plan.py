"""`cdrb plan`: sample plans from a model for given start/goal states."""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.configs import PlanConfig, PlanSummary
from cdrb_cli.envs.registry import family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.base import Planner, SampleResult
from cdrb_cli.methods.checkpoint import load_method
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.seeding import STREAM_PLAN, step_rng
from cdrb_cli.stages.avoid import Avoidance, mask_counts, prepare_planner, warn_unrouted
from cdrb_cli.stages.configure import check_plan_count


class SampledPlans(NamedTuple):
    """What :func:`sample_plans` returns (a tuple, in this order)."""

    plans: np.ndarray  # (Q*n, H, F), raw units
    pair_index: np.ndarray  # (Q*n,) the pair of each plan
    iterates: np.ndarray | None  # (Q*n, S, H, F) kept intermediate iterates
    iterate_steps: list[int] | None  # the diffusion step of each kept iterate
    seconds: float  # mean seconds per sampled batch


# ------------------------------------------------------------------------------------------------ new obstacles
def scene_spec(model, maze_map: Path | None, flag: str | None = None) -> EnvSpec:
    """The spec plans run in: the model's, or its task in the scene file ``maze_map`` (a maze map with walls added,
    Fetch boxes put down: obstacles the training data never saw; the family checks the file fits the model and
    warns when it opens space the data never covered). Errors name ``flag``, else the family's own flag."""
    spec = model.manifest.env
    if maze_map is None:
        return spec
    family = family_of(spec)
    new = family.with_map(spec, Path(maze_map)) if flag is None else family.with_map(spec, Path(maze_map), flag)
    warning = family.scene_change_warning(new)
    if warning:
        from cdrb_cli import ui

        ui.warn(warning)
    return new


#: points per planned step that the guidance cost also checks (between consecutive states), so a guided plan is
def sample_plans(
    method: Planner,
    starts: np.ndarray,
    goals: np.ndarray,
    n: int,
    seed: int,
    sampler=None,
    steps=None,
    keep_iterates: int = 0,
    batch_size: int = 256,
    device="cpu",
    avoid: Avoidance | None = None,
):
    """Plans for every (start, goal) pair, ``n`` per pair, in raw units, pinned exactly to the raw start/goal (with
    ``avoid``, each the best of its N samples, or repaired from a buffer route).

    Returns a :class:`SampledPlans` (plans, pair_index, iterates, iterate_steps, seconds per batch)."""
    norm = method.normalizer
    pair_index = np.repeat(np.arange(len(starts)), n)
    s_raw, g_raw = starts[pair_index], goals[pair_index]
    plans, iters, iter_steps, batch_times = [], [], None, []
    for b, a in enumerate(range(0, len(pair_index), batch_size)):
        sl = slice(a, a + batch_size)
        rng = step_rng(seed, STREAM_PLAN, b)
        out, res, seconds = _sampler_call(
            method, s_raw[sl], g_raw[sl], rng, sampler, steps, keep_iterates, device, avoid=avoid
        )
        batch_times.append(seconds)
        plans.append(out)
        if keep_iterates and res.iterates:
            iters.append(np.stack([norm.unnormalize(x.cpu().numpy().astype(np.float64)) for _, x in res.iterates], 1))
            iter_steps = [k for k, _ in res.iterates]
    it = np.concatenate(iters) if iters else None
    return SampledPlans(np.concatenate(plans), pair_index, it, iter_steps, float(np.mean(batch_times)))


def _sampler_call(
    method: Planner,
    starts,
    goals,
    rng,
    sampler,
    steps,
    keep_iterates=0,
    device="cpu",
    previous=None,
    repair_k=None,
    avoid: Avoidance | None = None,
):
    """One sampler call for raw start/goal states (n, obs_dim): normalized in, plans (n, H, F) out in raw units and
    pinned exactly to the raw states; with ``previous`` (raw plans) and ``repair_k``, a repair instead of a plan
    from scratch; with ``avoid``, N plans per pair in the same call and the best kept, plans from scratch repaired
    from buffer routes, and (``fallback_route_k``) pairs whose kept plan still crosses an obstacle tried again from
    a buffer route. Returns (plans, the method's SampleResult, seconds of the call, the route search and the
    best-of choice included)."""
    import torch

    t = time.perf_counter()
    scratch, reps = previous is None, 1 if avoid is None else avoid.best_of
    each_s, each_g = np.repeat(starts, reps, axis=0), np.repeat(goals, reps, axis=0)
    previous = None if previous is None else np.repeat(previous, reps, axis=0)
    if avoid is not None and avoid.route_k is not None and scratch:  # one route per pair, repaired N times
        routes = avoid.routes(starts, goals, method.horizon, method.feature_dim)
        previous, repair_k = np.repeat(routes, reps, axis=0), avoid.route_k
    searched = time.perf_counter() - t
    out, res, seconds = _restore(method, each_s, each_g, rng, previous, repair_k, sampler, steps, keep_iterates, device)
    t = time.perf_counter()
    if reps > 1:
        keep = avoid.choose(out)
        pick = torch.as_tensor(keep, device=res.plans.device)
        out, res = out[keep], SampleResult(plans=res.plans[pick], iterates=[(k, x[pick]) for k, x in res.iterates])
    if avoid is not None and avoid.fallback_route_k is not None and scratch and avoid.graph is not None:
        out, res = _route_fallback(method, out, res, starts, goals, rng, sampler, steps, device, avoid)
    if avoid is not None and avoid.retime and scratch:
        out, rows = avoid.retimed_plans(out)
        if len(rows):
            res = SampleResult(plans=_set_rows(method, res.plans.clone(), rows, out[rows]), iterates=res.iterates)
    return out, res, seconds + searched + (time.perf_counter() - t)  # the search and the choice count


def _restore(method: Planner, starts, goals, rng, previous, repair_k, sampler, steps, keep_iterates, device):
    """The method's own call for raw start/goal states (n, obs_dim): a plan from scratch, or with ``previous``
    (raw, (n, H, F)) a repair from step ``repair_k``; returns (raw plans pinned exactly, SampleResult, seconds)."""
    import torch

    def normalized(states):  # the state part of a normalized feature vector
        pad = np.zeros((len(states), method.feature_dim - method.obs_dim))
        z = method.normalizer.normalize(np.concatenate([states, pad], axis=1))[:, : method.obs_dim]
        return torch.as_tensor(z, dtype=torch.float32, device=device)

    st, gl = normalized(starts), normalized(goals)
    t = time.perf_counter()
    if repair_k is None:
        res = method.sample(st, gl, rng, sampler=sampler, steps=steps, keep_iterates=keep_iterates)
    else:
        prev = torch.as_tensor(method.normalizer.normalize(previous), dtype=torch.float32, device=device)
        res = method.repair(st, gl, prev, repair_k, rng, sampler=sampler, steps=steps)
    if str(device) != "cpu" and torch.cuda.is_available():
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t
    out = method.normalizer.unnormalize(res.plans.cpu().numpy().astype(np.float64))
    out[:, 0, method.pinned] = starts[:, method.pinned]  # pinned exactly in raw units too
    out[:, -1, method.pinned_end] = goals[:, method.pinned_end]
    return out, res, seconds


def _route_fallback(method: Planner, out, res, starts, goals, rng, sampler, steps, device, avoid: Avoidance):
    """The second try of ``avoid.fallback_route_k``: each pair whose kept plan in ``out`` (raw, (n, H, F)) steps
    through an obstacle, or leaves its start faster than the dynamics allow (:meth:`Avoidance.leaping`), is sampled
    again ``best_of`` times as a repair of its shortest buffer route from step k,
    and the best of its kept plan and those is kept (:meth:`Avoidance.choose`); with ``fallback_route_itself``, a
    pair whose kept plan then still crosses takes the route itself where the route crosses nothing. Returns (plans,
    SampleResult); the iterates kept of a pair tried again are those of its first try."""
    import torch

    bad = np.union1d(avoid.crossing(out), avoid.leaping(out))
    if not len(bad):
        return out, res
    avoid.rerouted += len(bad)
    reps = avoid.best_of
    each = avoid.routes(starts[bad], goals[bad], method.horizon, method.feature_dim)
    routes = np.repeat(each, reps, axis=0)
    s, g = np.repeat(starts[bad], reps, axis=0), np.repeat(goals[bad], reps, axis=0)
    again, res2, _ = _restore(method, s, g, rng, routes, avoid.fallback_route_k, sampler, steps, 0, device)
    shape = out.shape[1:]
    candidates = np.concatenate([out[bad][:, None], again.reshape(len(bad), reps, *shape)], axis=1)
    pick = avoid.choose(candidates.reshape(-1, *shape), per=reps + 1)
    out = out.copy()
    out[bad] = candidates.reshape(-1, *shape)[pick]
    first = res.plans[torch.as_tensor(bad, device=res.plans.device)][:, None]
    normal = torch.cat([first, res2.plans.reshape(len(bad), reps, *res2.plans.shape[1:])], dim=1)
    plans = res.plans.clone()
    plans[torch.as_tensor(bad, device=plans.device)] = normal.reshape(-1, *plans.shape[1:])[
        torch.as_tensor(pick, device=plans.device)
    ]
    if avoid.fallback_route_itself:
        counts = family_of(avoid.spec).crossing_counts
        states = slice(None), slice(None), slice(0, avoid.spec.obs_dim)
        kept, route = counts(avoid.spec, out[bad][states]), counts(avoid.spec, each[states])
        # a clear route only: a pair no route joined has the straight line here, which is no route of the buffer
        better = np.flatnonzero((np.asarray(route) == 0) & (np.asarray(kept) > 0))
        if len(better):
            avoid.route_kept += len(better)
            rows, sub = bad[better], each[better].copy()
            sub[:, 0, method.pinned] = starts[rows][:, method.pinned]  # a list of dims or a slice alike
            sub[:, -1, method.pinned_end] = goals[rows][:, method.pinned_end]
            out[rows] = sub
            _set_rows(method, plans, rows, sub)
    return out, SampleResult(plans=plans, iterates=res.iterates)


def _set_rows(method: Planner, plans, rows: np.ndarray, raw: np.ndarray):
    """``plans`` (the sampler's normalized tensor) with ``rows`` set, in place, to the raw plans ``raw``; returns
    it. What replaced a kept plan after the sampler (a buffer route, a retimed plan) shows in its result too."""
    import torch

    z = torch.as_tensor(method.normalizer.normalize(raw), dtype=plans.dtype, device=plans.device)
    plans[torch.as_tensor(rows, device=plans.device)] = z
    return plans


def replan_batch(
    method: Planner,
    starts: np.ndarray,
    goals: np.ndarray,
    rng: np.random.Generator,
    sampler=None,
    steps=None,
    previous: np.ndarray | None = None,
    repair_k: int | None = None,
    device="cpu",
    avoid: Avoidance | None = None,
) -> tuple[np.ndarray, float]:
    """One plan per (start, goal) state pair, in raw units and pinned exactly: from scratch, or with ``previous``
    (raw plans (n, H, F), already shifted to the starts) and ``repair_k``, repaired from degradation step k
    (:meth:`~cdrb_cli.methods.base.Planner.repair`; ``steps`` then counts the repair's denoising steps).
    Returns (plans (n, H, F), seconds of the sampler call)."""
    out, _, seconds = _sampler_call(method, starts, goals, rng, sampler, steps, 0, device, previous, repair_k, avoid)
    return out, seconds


def load_planner(model, device="cpu", ema: bool = True) -> Planner:
    """The planner of a model artifact (a one-line error for a policy)."""
    entry = METHODS.get(model.manifest.config.method.name)
    if entry.kind != "planner":
        raise BadInput(
            f"{model.path}: {entry.name} is a policy (it acts step by step and makes no plans)",
            hint="evaluate it closed loop with `cdrb eval MODEL`",
        )
    from cdrb_cli.lazy import torch

    with torch.random.fork_rng(devices=[]):  # building the nets draws initial weights: the caller's stream is kept
        return load_method(model, device=device, ema=ema)


def check_sample_steps(model, sample_steps: int | None, where: str | None = None) -> None:
    """Refuse more denoising steps than the model's T (fewer than all is what ``sample_steps`` is for); ``where``:
    how the user gave the value, for the error."""
    steps = getattr(model.manifest.config.method, "diffusion_steps", None)
    if sample_steps is not None and steps is not None and sample_steps > steps:
        raise BadInput(
            f"{where or f'sample_steps = {sample_steps}'}: the model has T = {steps} diffusion steps, so at most "
            f"{steps}",
            hint="leave it out for all of them, or give fewer",
        )


def make_plans(
    model,
    starts,
    goals,
    config: PlanConfig,
    out,
    device="cpu",
    spec: EnvSpec | None = None,
    route_buffer=None,
):
    """`cdrb plan`: plans for every (start, goal) pair in ``spec``'s scene (default: the model's), written to
    ``out``; ``route_buffer``: the buffer artifact of ``config.avoid.route_buffer`` (a parent of the plans)."""
    spec = spec or model.manifest.env
    check_sample_steps(model, config.sample_steps)
    check_plan_count(model, len(starts), config)  # before the sampler allocates for them
    method = load_planner(model, device=device, ema=config.use_ema)
    METHODS.get(method.name).check_sampler(config.sampler)
    avoid = prepare_planner(method, spec, config.avoid, route_buffer)
    plans, pair_index, iterates, iter_steps, sec = sample_plans(
        method,
        starts,
        goals,
        config.n,
        config.seed,
        config.sampler,
        config.sample_steps,
        config.keep_iterates,
        config.batch,
        device,
        avoid,
    )
    warn_unrouted(avoid)
    # judged as the file stores them (float32): a state on an obstacle's edge must read the same in the summary, the
    # warnings and a later look at the file
    plans = plans.astype(np.float32).astype(np.float64)
    family = family_of(spec)
    in_wall = family.in_collision(spec, plans[..., : spec.obs_dim])
    summary = PlanSummary(
        pairs=int(len(starts)),
        plans=int(len(plans)),
        in_wall_fraction=float(in_wall.mean()),
        plans_with_wall_states=int(in_wall.any(axis=1).sum()),
        plans_crossing=int(np.asarray(family.path_in_collision(spec, plans[..., : spec.obs_dim])).sum()),
        masked=mask_counts(method, avoid),
        seconds_per_batch=round(sec, 6),
        seconds_per_plan=round(sec / min(config.batch, len(plans)), 6),
        device=str(device),
    )
    manifest = artifacts.make_manifest(
        "plans",
        env=spec,
        config=config,
        seed=config.seed,
        parents=[model] if route_buffer is None else [model, route_buffer],
        summary=summary,
        method=method.name,
    )
    arrays = {
        "plans": plans.astype(np.float32),
        "pair_index": pair_index.astype(np.int64),
        "starts": starts.astype(np.float32),
        "goals": goals.astype(np.float32),
        "in_wall": in_wall,
    }
    if iterates is not None:
        arrays["iterates"] = iterates.astype(np.float32)
        arrays["iterate_steps"] = np.asarray(iter_steps, dtype=np.int64)
    artifacts.save(out, "plans", manifest, arrays)
    return artifacts.load(out, "plans")


def plan_points(spec: EnvSpec, start: list[str], goal: list[str], pairs: int, seed: int):
    """The (starts, goals) full states of `cdrb plan`: ``pairs`` drawn by the protocol (stream plan), or the
    ``--start``/``--goal`` points as typed (one goal for every start, or one per start)."""
    from cdrb_cli.seeding import STREAM_PLAN

    family = family_of(spec)
    if pairs:
        if start or goal:
            raise BadInput("--pairs with --start/--goal", hint="give either explicit points or --pairs N")
        starts, goals = family.reset_states(spec, family.draw_episodes(spec, pairs, seed, STREAM_PLAN))
        return starts, family.goal_state(spec, goals)
    if not start or not goal:
        raise BadInput("no start/goal given", hint=f"pass --start and --goal ({family.point_format}), or --pairs N")
    if len(goal) == 1 and len(start) > 1:
        goal = goal * len(start)
    if len(goal) != len(start):
        raise BadInput(f"{len(start)} --start but {len(goal)} --goal", hint="give one goal per start, or one")
    return (
        np.array([family.parse_point(spec, t, "--start") for t in start]),
        np.array([family.parse_point(spec, t, "--goal") for t in goal]),
    )


def draw_plans(result, spec: EnvSpec, path) -> None:
    """A plans artifact's plans over the scene (with the iterates it kept), to a picture at ``path``."""
    from cdrb_cli.envs.render import plot_plans

    a, sm = result.arrays, result.manifest.summary
    plot_plans(
        spec,
        a["plans"],
        path,
        starts=a["starts"],
        goals=a["goals"],
        in_wall=a["in_wall"],
        title=f"{result.manifest.method}: {sm.plans} plans, {sm.in_wall_fraction:.1%} states in obstacles",
        iterates=a.get("iterates"),
        iterate_steps=a.get("iterate_steps"),
    )
