"""`cdrb plan`: sample plans from a model for given start/goal states."""

from __future__ import annotations

import time

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.configs import PlanConfig, PlanSummary
from cdrb_cli.envs.maze import in_collision
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.seeding import STREAM_PLAN, step_rng


def parse_state(text: str, flag: str, spec: EnvSpec) -> np.ndarray:
    """'x,y' (at rest) or a full state 'x,y,vx,vy' -> a state vector; one-line errors."""
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v != ""]
    except ValueError:
        raise BadInput(f"{flag} {text!r}: not a list of numbers", hint="write e.g. 0,0 or 0,0,0,0") from None
    n_pos = len(spec.goal_dims)
    if len(values) == n_pos:
        state = np.zeros(spec.obs_dim)
        state[spec.goal_dims] = values
    elif len(values) == spec.obs_dim:
        state = np.array(values)
    else:
        raise BadInput(f"{flag} {text!r}: expected {n_pos} or {spec.obs_dim} numbers", hint="write e.g. 0,0")
    if not np.all(np.isfinite(state)):
        raise BadInput(f"{flag} {text!r}: values must be finite", hint="write e.g. 0,0")
    return state


def check_state(state: np.ndarray, flag: str, spec: EnvSpec) -> None:
    ob = spec.obstacles
    pos = state[ob.dims]
    if np.any(pos < np.asarray(ob.low)) or np.any(pos > np.asarray(ob.high)):
        raise BadInput(
            f"{flag} {','.join(f'{v:g}' for v in pos)}: outside the map "
            f"(x in [{ob.low[0]:g}, {ob.high[0]:g}], y in [{ob.low[1]:g}, {ob.high[1]:g}])",
            hint="choose a point inside the maze",
        )
    if in_collision(state[None], ob)[0]:
        raise BadInput(
            f"{flag} {','.join(f'{v:g}' for v in pos)}: inside a wall (the agent, radius {ob.inflate:g}, overlaps it)",
            hint="choose a free point (`cdrb collect --plot` shows the map)",
        )


def sample_plans(
    method,
    net,
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

    Returns (plans (Q*n, H, F), pair_index, iterates (Q*n, S, H, F) or None, iterate_steps, seconds per batch)."""
    import torch

    norm = method.normalizer
    obs = method.obs_dim
    q = len(starts)
    pair_index = np.repeat(np.arange(q), n)
    s_raw, g_raw = starts[pair_index], goals[pair_index]
    pad = np.zeros((len(pair_index), method.feature_dim))
    s_norm = norm.normalize(np.concatenate([s_raw, pad[:, obs:]], axis=1))[:, :obs]
    g_norm = norm.normalize(np.concatenate([g_raw, pad[:, obs:]], axis=1))[:, :obs]
    plans, iters, iter_steps, batch_times = [], [], None, []
    for b, a in enumerate(range(0, len(pair_index), batch_size)):
        sl = slice(a, a + batch_size)
        rng = step_rng(seed, STREAM_PLAN, b)
        st = torch.as_tensor(s_norm[sl], dtype=torch.float32, device=device)
        gl = torch.as_tensor(g_norm[sl], dtype=torch.float32, device=device)
        t = time.perf_counter()
        res = method.sample(net, st, gl, rng, sampler=sampler, steps=steps, keep_iterates=keep_iterates)
        if device != "cpu" and torch.cuda.is_available():
            torch.cuda.synchronize()
        batch_times.append(time.perf_counter() - t)
        plans.append(norm.unnormalize(res.plans.cpu().numpy().astype(np.float64)))
        if keep_iterates and res.iterates:
            iters.append(np.stack([norm.unnormalize(x.cpu().numpy().astype(np.float64)) for _, x in res.iterates], 1))
            iter_steps = [k for k, _ in res.iterates]
    out = np.concatenate(plans)
    out[:, 0, :obs] = s_raw  # pinned exactly in raw units too
    out[:, -1, :obs] = g_raw
    it = np.concatenate(iters) if iters else None
    return out, pair_index, it, iter_steps, float(np.mean(batch_times))


def make_plans(model, starts, goals, config: PlanConfig, out, device="cpu", batch_size: int = 256):
    from cdrb_cli.stages.train import load_planner

    spec = model.manifest.env
    method, ema = load_planner(model, device=device)
    net = ema if config.use_ema else method.net
    if config.sampler not in method.samplers and method.samplers:
        raise BadInput(f"--sampler {config.sampler}: {method.name} samplers are {', '.join(method.samplers)}")
    plans, pair_index, iterates, iter_steps, sec = sample_plans(
        method,
        net,
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
    in_wall = in_collision(plans[..., : spec.obs_dim], spec.obstacles)
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
