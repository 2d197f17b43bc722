"""`cdrb plan`: sample plans from a model for given start/goal states."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.configs import ROUTE_STEPS, AvoidConfig, MaskCounts, PlanConfig, PlanSummary
from cdrb_cli.envs.registry import family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.base import Planner, SampleResult
from cdrb_cli.methods.checkpoint import load_method
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.seeding import STREAM_PLAN, step_rng
from cdrb_cli.stages.configure import check_plan_count
from cdrb_cli.stages.routes import BufferGraph


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
#: pushed off a jump through a wall and not only off states inside one
GUIDE_SUBSTEPS = 4


#: a plan's first step may be this many times what the dynamics allow in one plan step: best-of choices prefer
#: plans within it, and `cdrb plan` warns when the median plan leaves its start faster
FIRST_STEP_TOLERANCE = 1.5


@dataclass
class Avoidance:
    """What keeps a planner's plans out of the obstacles of ``spec`` at plan time (:func:`prepare_planner`):
    best-of-N by the collision test, and routes through the buffer to start repairs from."""

    spec: EnvSpec
    best_of: int = 1
    graph: BufferGraph | None = None
    route_k: int | None = None
    fallback_route_k: int | None = None
    fallback_route_itself: bool = False
    masked: dict[str, int] | None = None  # what masking the buffer removed
    unrouted: int = 0  # pairs no buffer route joined (planned from scratch)
    rerouted: int = 0  # pairs sampled again from a buffer route because every plan from scratch crossed or leapt
    route_kept: int = 0  # pairs whose every plan and repair crossed, planned by the buffer route itself
    first_step: bool = False  # the first step counts in the choice and calls for the second try
    retime: bool = False  # a kept plan that still leaps is respaced along its own path
    retimed: int = 0  # plans retimed so
    #: what the dynamics allow in one plan step (the family's max step x the model's stride); None: unknown
    step_limit: float | None = None

    def choose(self, plans: np.ndarray, per: int | None = None) -> np.ndarray:
        """Indices into ``plans`` (P * per, H, F), raw and grouped by pair (``per``: plans per pair, default
        ``best_of``), of the plan kept for each pair: the one with the fewest steps through an obstacle (none, when
        one has none); with ``first_step``, among those one whose first step leaves the start by no more than
        :data:`FIRST_STEP_TOLERANCE` times ``step_limit`` (a robot can follow it from where it is), where one does;
        then the shortest path."""
        per = per or self.best_of
        family = family_of(self.spec)
        states = plans[..., : self.spec.obs_dim]
        counts = family.crossing_counts(self.spec, states).reshape(-1, per)
        dims = list(self.spec.obstacles.dims)
        length = np.linalg.norm(np.diff(states[..., dims], axis=-2), axis=-1).sum(-1).reshape(-1, per)
        leaps = self._leaps(plans).reshape(-1, per)
        order = np.lexsort((length, leaps, counts), axis=-1) if counts.size else counts
        return np.arange(len(counts)) * per + order[:, 0]

    def crossing(self, plans: np.ndarray) -> np.ndarray:
        """Indices of the raw plans (n, H, F) with a step through an obstacle."""
        states = plans[..., : self.spec.obs_dim]
        return np.flatnonzero(np.asarray(family_of(self.spec).crossing_counts(self.spec, states)) > 0)

    def leaping(self, plans: np.ndarray) -> np.ndarray:
        """With ``first_step``, indices of the raw plans (n, H, F) whose first step leaves the start by more than
        :data:`FIRST_STEP_TOLERANCE` times ``step_limit`` (none without it, or when the limit is unknown)."""
        return np.flatnonzero(self._leaps(plans))

    def _leaps(self, plans: np.ndarray, on: bool | None = None) -> np.ndarray:
        """Per raw plan (..., H, F): whether ``first_step`` (or ``on``) is on and its first step leaves the start by
        more than :data:`FIRST_STEP_TOLERANCE` times ``step_limit`` (all False without it or a known limit)."""
        on = self.first_step if on is None else on
        if not (on and self.step_limit) or plans.shape[-2] < 2:
            return np.zeros(plans.shape[:-2], dtype=bool)
        dims = list(self.spec.obstacles.dims)
        first = np.linalg.norm(plans[..., 1, dims] - plans[..., 0, dims], axis=-1)
        return first > FIRST_STEP_TOLERANCE * self.step_limit

    def retimed_plans(self, plans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """With ``retime``, (the raw plans (n, H, F) with each clear one that leaps from its start respaced evenly
        by arc length along its own path where that brings its first step within the tolerance, the indices of
        those); the plans unchanged and no index without it. The ends stay exactly where they were and every new
        state lies on one of the plan's own straight steps, so a plan that steps through no obstacle still steps
        through none (a plan through one keeps its timing: respaced, more of its states could fall inside)."""
        from cdrb_cli.stages.routes import resample_evenly

        leaps = self._leaps(plans, on=self.retime)
        if leaps.any():
            counts = family_of(self.spec).crossing_counts(self.spec, plans[..., : self.spec.obs_dim])
            leaps &= np.asarray(counts) == 0
        rows = np.flatnonzero(leaps)
        if not len(rows):
            return plans, rows
        dims = list(self.spec.obstacles.dims)
        even = np.stack([resample_evenly(plans[i], dims, plans.shape[1]) for i in rows])
        ok = ~self._leaps(even, on=True)
        out = plans.copy()
        out[rows[ok]] = even[ok]
        self.retimed += int(ok.sum())
        return out, rows[ok]

    def routes(self, starts: np.ndarray, goals: np.ndarray, horizon: int, features: int) -> np.ndarray | None:
        """Raw buffer routes (n, horizon, features) for raw start/goal states (n, obs_dim); a pair with no route
        gets the straight line (counted in ``unrouted``)."""
        pad = np.zeros((len(starts), features - starts.shape[1]))
        s, g = np.concatenate([starts, pad], 1), np.concatenate([goals, pad], 1)
        out = []
        for a, b in zip(s, g):
            r = self.graph.route(a, b, horizon)
            if r is None:
                self.unrouted += 1
                r = np.linspace(a, b, horizon)
            out.append(r)
        return np.stack(out)


def prepare_planner(method: Planner, spec: EnvSpec, avoid: AvoidConfig, route_buffer=None) -> Avoidance:
    """Apply ``avoid`` to a loaded planner for the scene of ``spec``: mask its buffer, set its collision guidance
    (the family's cost of each state and of points between consecutive states), build the buffer graph its routes
    come from (``route_buffer``: a buffer artifact, for a planner without its own). Returns the
    :class:`Avoidance` the sampler calls use."""
    family = family_of(spec)
    norm, obs = method.normalizer, method.obs_dim
    out = Avoidance(
        spec,
        best_of=avoid.best_of,
        route_k=avoid.route_k,
        fallback_route_k=avoid.fallback_route_k,
        fallback_route_itself=avoid.fallback_route_itself,
        first_step=avoid.first_step,
        retime=avoid.retime,
    )
    out.step_limit = family.plan_step_limit(spec, method.config.stride)
    if avoid.mask_buffer:

        def collides(features: np.ndarray) -> np.ndarray:
            return np.asarray(family.in_collision(spec, norm.unnormalize(features)[..., :obs]), dtype=bool)

        try:
            out.masked = method.mask(collides)
        except ValueError as exc:
            raise BadInput(f"avoid.mask_buffer: {exc}", hint="the new obstacles cover the whole buffer") from None
    for field in ROUTE_STEPS:
        k, top = getattr(avoid, field), method.repair_steps()
        if k is not None and (top is None or k > top):
            raise BadInput(
                f"avoid.{field} = {k}: {method.name} repairs from steps 1..{top}",
                hint=f"use avoid.{field}={max(1, (top or 8) // 8)}",
            )
    if any(getattr(avoid, field) is not None for field in ROUTE_STEPS):
        out.graph = buffer_graph(method, spec, avoid, route_buffer)
    if avoid.guide_scale > 0:
        raw_cost = family.collision_cost(spec)
        fractions = np.arange(GUIDE_SUBSTEPS) / GUIDE_SUBSTEPS

        def cost(x):
            import torch

            states = norm.unnormalize(x)[..., :obs]
            w = torch.as_tensor(fractions, dtype=x.dtype, device=x.device)[None, None, :, None]
            pts = states[:, :-1, None, :] * (1 - w) + states[:, 1:, None, :] * w  # (P, H-1, substeps, obs)
            return raw_cost(pts).sum(dim=(1, 2)) + raw_cost(states[:, -1]).reshape(len(x))

        method.set_guide(cost, avoid.guide_scale)
    return out


def buffer_graph(method: Planner, spec: EnvSpec, avoid: AvoidConfig, route_buffer=None) -> BufferGraph:
    """The graph of buffer states that routes go through for ``avoid`` in the scene of ``spec``: the planner's own
    (masked) buffer, or ``route_buffer`` (the artifact of ``avoid.route_buffer``)."""
    if avoid.route_buffer is not None and route_buffer is None:
        raise ValueError("config.avoid.route_buffer is set: pass its buffer artifact")
    return BufferGraph(spec, route_states(method, spec, route_buffer), clearance=avoid.route_clearance)


def load_route_buffer(path: Path | None):
    """The buffer artifact of ``avoid.route_buffer`` (None without it); a one-line error naming the setting."""
    if path is None:
        return None
    try:
        return artifacts.load(path, "buffer")
    except BadInput as exc:
        raise BadInput(f"avoid.route_buffer: {exc.message}", hint=exc.hint) from None


def route_states(method: Planner, spec: EnvSpec, route_buffer=None) -> np.ndarray:
    """Raw feature rows (K, method.feature_dim) that buffer routes go through: the model's own (masked) buffer,
    or the states of the buffer artifact ``route_buffer`` (which must be of the model's environment)."""
    if route_buffer is None:
        return method.normalizer.unnormalize(method.ball.points)
    states = buffer_states(route_buffer, spec, method.spec.id)  # the model's own task, before any map change
    pad = np.zeros((len(states), method.feature_dim - spec.obs_dim))
    return np.concatenate([states, pad], axis=1)


def buffer_states(route_buffer, spec: EnvSpec, task: str) -> np.ndarray:
    """The raw states (K, obs_dim) of the buffer artifact ``route_buffer``, which must be of the model's task
    ``task``."""
    from cdrb_cli.buffer import Normalizer

    env = route_buffer.manifest.env
    if env.obs_dim != spec.obs_dim or env.id != task:
        raise BadInput(
            f"--route-buffer {route_buffer.path}: a buffer of {env.id}, but the model plans in {task}",
            hint="cluster the model's own demos (`cdrb cluster DEMOS`)",
        )
    return Normalizer(route_buffer.low, route_buffer.high).unnormalize(route_buffer.points)[:, : spec.obs_dim]


def warn_unrouted(avoid: Avoidance | None) -> None:
    """Say how many pairs were tried again from a buffer route, and how many no buffer route joined (each was
    repaired from the straight line instead)."""
    from cdrb_cli import ui

    if avoid is not None and avoid.retimed:
        ui.log(
            f"{avoid.retimed} plan(s) that left their start faster than the dynamics allow were retimed along their "
            "own path (avoid.retime)"
        )
    if avoid is not None and avoid.rerouted:
        ui.log(
            f"{avoid.rerouted} start/goal pair(s) whose every plan crossed an obstacle or left the start faster "
            "than the dynamics allow were tried again from a buffer route "
            f"(avoid.fallback_route_k = {avoid.fallback_route_k})"
        )
    if avoid is not None and avoid.route_kept:
        ui.log(
            f"{avoid.route_kept} start/goal pair(s) whose every plan and repair crossed an obstacle were given the "
            "buffer route itself (avoid.fallback_route_itself)"
        )
    if avoid is not None and avoid.unrouted:
        ui.warn(
            f"buffer routes: no route through the buffer joined {avoid.unrouted} start/goal pair(s); they were "
            "repaired from the straight line (the buffer has no free steps around them)"
        )


def mask_counts(method: Planner, avoid: Avoidance | None) -> MaskCounts | None:
    """What masking did so far: the counts from :func:`prepare_planner` and the method's re-draw tallies."""
    if avoid is None or avoid.masked is None:
        return None
    return MaskCounts(**avoid.masked, redrawn=int(method.redrawn), unreachable=int(method.unreachable))


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
