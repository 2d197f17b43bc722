"""`cdrb plan`: sample plans from a model for given start/goal states."""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.configs import PlanConfig, PlanSummary
from cdrb_cli.envs.registry import family_of
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.base import Planner
from cdrb_cli.methods.checkpoint import load_method
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.seeding import STREAM_PLAN, step_rng


class SampledPlans(NamedTuple):
    """What :func:`sample_plans` returns (a tuple, in this order)."""

    plans: np.ndarray  # (Q*n, H, F), raw units
    pair_index: np.ndarray  # (Q*n,) the pair of each plan
    iterates: np.ndarray | None  # (Q*n, S, H, F) kept intermediate iterates
    iterate_steps: list[int] | None  # the diffusion step of each kept iterate
    seconds: float  # mean seconds per sampled batch


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
):
    """Plans for every (start, goal) pair, ``n`` per pair, in raw units, pinned exactly to the raw start/goal.

    Returns a :class:`SampledPlans` (plans, pair_index, iterates, iterate_steps, seconds per batch)."""
    norm = method.normalizer
    pair_index = np.repeat(np.arange(len(starts)), n)
    s_raw, g_raw = starts[pair_index], goals[pair_index]
    plans, iters, iter_steps, batch_times = [], [], None, []
    for b, a in enumerate(range(0, len(pair_index), batch_size)):
        sl = slice(a, a + batch_size)
        rng = step_rng(seed, STREAM_PLAN, b)
        out, res, seconds = _sampler_call(method, s_raw[sl], g_raw[sl], rng, sampler, steps, keep_iterates, device)
        batch_times.append(seconds)
        plans.append(out)
        if keep_iterates and res.iterates:
            iters.append(np.stack([norm.unnormalize(x.cpu().numpy().astype(np.float64)) for _, x in res.iterates], 1))
            iter_steps = [k for k, _ in res.iterates]
    it = np.concatenate(iters) if iters else None
    return SampledPlans(np.concatenate(plans), pair_index, it, iter_steps, float(np.mean(batch_times)))


def _sampler_call(
    method: Planner, starts, goals, rng, sampler, steps, keep_iterates=0, device="cpu", previous=None, repair_k=None
):
    """One sampler call for raw start/goal states (n, obs_dim): normalized in, plans (n, H, F) out in raw units and
    pinned exactly to the raw states; with ``previous`` (raw plans) and ``repair_k``, a repair instead of a plan
    from scratch. Returns (plans, the method's SampleResult, seconds of the call)."""
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
) -> tuple[np.ndarray, float]:
    """One plan per (start, goal) state pair, in raw units and pinned exactly: from scratch, or with ``previous``
    (raw plans (n, H, F), already shifted to the starts) and ``repair_k``, repaired from degradation step k
    (:meth:`~cdrb_cli.methods.base.Planner.repair`; ``steps`` then counts the repair's denoising steps).
    Returns (plans (n, H, F), seconds of the sampler call)."""
    out, _, seconds = _sampler_call(method, starts, goals, rng, sampler, steps, 0, device, previous, repair_k)
    return out, seconds


def load_planner(model, device="cpu", ema: bool = True) -> Planner:
    """The planner of a model artifact (a one-line error for a policy)."""
    entry = METHODS.get(model.manifest.config.method.name)
    if entry.kind != "planner":
        raise BadInput(
            f"{model.path}: {entry.name} is a policy (it acts step by step and makes no plans)",
            hint="evaluate it closed loop with `cdrb eval MODEL`",
        )
    return load_method(model, device=device, ema=ema)


def make_plans(model, starts, goals, config: PlanConfig, out, device="cpu", batch_size: int = 256):
    spec = model.manifest.env
    method = load_planner(model, device=device, ema=config.use_ema)
    METHODS.get(method.name).check_sampler(config.sampler)
    plans, pair_index, iterates, iter_steps, sec = sample_plans(
        method,
        starts,
        goals,
        config.n,
        config.seed,
        config.sampler,
        config.sample_steps,
        config.keep_iterates,
        batch_size,
        device,
    )
    in_wall = family_of(spec).in_collision(spec, plans[..., : spec.obs_dim])
    summary = PlanSummary(
        pairs=int(len(starts)),
        plans=int(len(plans)),
        in_wall_fraction=float(in_wall.mean()),
        plans_with_wall_states=int(in_wall.any(axis=1).sum()),
        seconds_per_batch=round(sec, 6),
        seconds_per_plan=round(sec / min(batch_size, len(plans)), 6),
        device=str(device),
    )
    manifest = artifacts.make_manifest(
        "plans", env=spec, config=config, seed=config.seed, parents=[model], summary=summary, method=method.name
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


#: a plan's first step may be this many times what the dynamics allow in one plan step before `cdrb plan` warns
FIRST_STEP_TOLERANCE = 1.5


def disconnected_warning(spec, plans: np.ndarray, stride: int) -> str | None:
    """One line when plans do not start where the robot is (a median first step over ``FIRST_STEP_TOLERANCE`` times
    what the dynamics allow in one plan step) or pass through an obstacle (a state in one, or a straight step
    between two states through one); None when neither. Longer steps later in a plan are normal (plans are paths
    the controller follows at its own pace) and not warned about."""
    family = family_of(spec)
    states = np.asarray(plans)[..., : spec.obs_dim].reshape(-1, plans.shape[-2], spec.obs_dim)
    problems = []
    crossing = np.asarray(family.path_in_collision(spec, states), dtype=bool)
    if crossing.any():
        problems.append(f"{int(crossing.sum())} of {len(states)} plans pass through an obstacle")
    max_step = family.max_step(spec)
    if max_step is not None and states.shape[1] > 1:
        allowed = max_step * stride
        dims = list(spec.obstacles.dims)
        first = float(np.median(np.linalg.norm(states[:, 1, dims] - states[:, 0, dims], axis=-1)))
        if first > FIRST_STEP_TOLERANCE * allowed:
            problems.append(
                f"the first planned step is {first:.2f} (median), {first / allowed:.1f}x the {allowed:.2f} the "
                "dynamics allow in one plan step"
            )
    if not problems:
        return None
    return (
        "; ".join(problems) + ": the start may lie where the training data never starts "
        "(`cdrb collect --starts anywhere`, docs/design.md 'Plans from anywhere')"
    )
