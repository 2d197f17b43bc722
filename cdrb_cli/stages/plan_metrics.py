"""Measurements `cdrb report` takes from the plans an eval stored (the eval's summary does not hold them): the first
planned step against the allowed one, crossings of obstacles a scene added after training, crossings of the walls
alone (the workspace's bounds left out), and crossings by body.

An eval also stores them per episode beside its plans (:func:`plan_measures`), so one saved without its plans
(`cdrb eval --no-plans`, `cdrb export EVAL --compact`) gives the same figures; an eval written before they were
stored has them computed from its plans."""

from __future__ import annotations

import numpy as np

FIRST_STEP = "episodes/plan_first_step"  #: the first planned step's length in the obstacle dims
NEW_CROSSING = "episodes/plan_crosses_new_obstacle"  #: a state in, or a step through, an obstacle added after training
WALL_CROSSING = "episodes/plan_crosses_wall"  #: a state in, or a step through, a wall (the workspace not counted)
PLAN_STATES = "episodes/plan_states"  #: the planned states of the episode's (first) plan
BODIES = "bodies/"  #: bodies/<name>/crossing (per episode) and bodies/<name>/states_in_obstacle (a count)


def plan_measures(spec, plans: np.ndarray) -> dict[str, np.ndarray]:
    """Every per-episode measure of this module, from the episodes' (first) plans (E, H, features) in raw units, as
    the eval stores them: their dataset name -> array with one entry per episode. The arithmetic is the one the
    rates below apply to plans, so stored and recomputed figures are the same numbers."""
    from cdrb_cli.envs.registry import family_of

    family, plans = family_of(spec), np.asarray(plans)
    states = plans[..., : spec.obs_dim]
    out = {PLAN_STATES: np.full(len(plans), plans.shape[1], dtype=np.int64)}
    if plans.shape[1] >= 2:
        out[FIRST_STEP] = _first_steps(spec, plans)
    new = family.new_obstacle_crossings(spec, states)
    if new is not None:
        out[NEW_CROSSING] = np.asarray(new, dtype=bool)
    walls = family.wall_crossings(spec, states)
    if walls is not None:
        out[WALL_CROSSING] = np.asarray(walls, dtype=bool)
    for name, hit in (family.crossings_by_body(spec, states) or {}).items():
        out[f"{BODIES}{name}/crossing"] = np.asarray(hit, dtype=bool)
    for name, hit in (family.collisions_by_body(spec, states) or {}).items():
        out[f"{BODIES}{name}/states_in_obstacle"] = np.asarray(hit, dtype=bool).sum(axis=-1, dtype=np.int64)
    return out


def _first_steps(spec, plans: np.ndarray) -> np.ndarray:
    dims = list(spec.obstacles.dims)
    return np.linalg.norm(plans[:, 1, dims] - plans[:, 0, dims], axis=-1)


def first_step_ratio(evals) -> float | None:
    """The median, over every episode of ``evals``, of the first planned step's length (in the obstacle dims)
    against what the dynamics allow in one plan step: about 1 when plans start where the robot is, far above 1 when
    a plan leaves its pinned start at once. None for policies, evals with neither plans nor the stored measure, or
    an unknown limit."""
    ratios = []
    for ev in evals:
        step, plans = ev.arrays.get(FIRST_STEP), ev.arrays.get("plans")
        limit = ev.arrays.get("episodes/plan_step_limit")
        if step is None and plans is not None and plans.shape[1] >= 2:
            step = _first_steps(ev.manifest.env, plans)
        if step is None or limit is None or not (np.asarray(limit) > 0).all():
            return None
        ratios.append(step / np.asarray(limit))
    return float(np.median(np.concatenate(ratios))) if ratios else None


def new_crossing_rates(ev) -> list[float] | None:
    """Per evaluation seed, the share of episodes whose (first) plan has a state in, or a step through, an obstacle
    the training scene did not have (walls added to a maze, boxes put down in a Fetch scene); None when the eval
    ran in its training scene or stored neither plans nor this measure."""
    return _stored_or_measured(
        ev, NEW_CROSSING, lambda family, spec, states: family.new_obstacle_crossings(spec, states)
    )


def wall_crossing_rates(ev) -> list[float] | None:
    """Per evaluation seed, the share of episodes whose (first) plan has a state in, or a step through, a wall, the
    workspace's bounds not counted; None for a family where that is the crossing test itself, or an eval that
    stored neither plans nor this measure."""
    return _stored_or_measured(ev, WALL_CROSSING, lambda family, spec, states: family.wall_crossings(spec, states))


def _stored_or_measured(ev, name: str, measure) -> list[float] | None:
    """Per evaluation seed, the mean of the per-episode measure ``name`` the eval stored, or else of ``measure(family,
    spec, planned states)`` on its plans; None where neither gives one."""
    from cdrb_cli.envs.registry import family_of

    hits, plans, spec = ev.arrays.get(name), ev.arrays.get("plans"), ev.manifest.env
    if hits is None and plans is not None:
        hits = measure(family_of(spec), spec, np.asarray(plans)[..., : spec.obs_dim])
    return None if hits is None else _seed_means(ev, hits)


def body_crossing_rates(ev) -> dict[str, list[float]] | None:
    """Per body the family's collision test moves (Fetch: gripper, block), per evaluation seed, the share of
    episodes whose (first) plan has that body in, or stepping through, an obstacle; None for a family with one body
    or an eval that stored neither plans nor the per-body measures."""
    stored = _stored_bodies(ev, "crossing")
    if stored is not None:
        return {name: _seed_means(ev, hit) for name, hit in stored.items()}
    return _per_body(ev, lambda family, spec, states: family.crossings_by_body(spec, states))


def body_state_rates(ev) -> dict[str, list[float]] | None:
    """As :func:`body_crossing_rates`, the share of planned states with that body in an obstacle."""
    stored = _stored_bodies(ev, "states_in_obstacle")
    if stored is not None:
        seeds, states = np.asarray(ev.arrays["episodes/seed"]), np.asarray(ev.arrays[PLAN_STATES])
        order = dict.fromkeys(seeds.tolist())
        return {
            name: [float(count[seeds == s].sum() / states[seeds == s].sum()) for s in order]
            for name, count in stored.items()
        }
    return _per_body(ev, lambda family, spec, states: family.collisions_by_body(spec, states))


def _stored_bodies(ev, measure: str) -> dict[str, np.ndarray] | None:
    """``bodies/<name>/<measure>`` of the eval, by body in the family's order; None when it stored none (one body,
    or an eval written before they were stored)."""
    from cdrb_cli.envs.registry import family_of

    suffix = f"/{measure}"
    found = {
        n[len(BODIES) : -len(suffix)]: a for n, a in ev.arrays.items() if n.startswith(BODIES) and n.endswith(suffix)
    }
    if not found:
        return None
    spec = ev.manifest.env
    order = family_of(spec).collisions_by_body(spec, np.zeros((1, spec.obs_dim))) or {}
    return {name: found[name] for name in [*[n for n in order if n in found], *sorted(set(found) - set(order))]}


def _per_body(ev, measure) -> dict[str, list[float]] | None:
    """``measure(family, spec, planned states)`` (a boolean array per body, over plans or over their states) averaged
    per evaluation seed; None where it gives none or the eval stored no plans."""
    from cdrb_cli.envs.registry import family_of

    plans, spec = ev.arrays.get("plans"), ev.manifest.env
    if plans is None:
        return None
    bodies = measure(family_of(spec), spec, np.asarray(plans)[..., : spec.obs_dim])
    return None if bodies is None else {name: _seed_means(ev, hit) for name, hit in bodies.items()}


def _seed_means(ev, hit: np.ndarray) -> list[float]:
    """The mean of ``hit`` (one row per episode of ``ev``, booleans over plans or their states) per evaluation seed,
    in the order the seeds first appear."""
    seeds = np.asarray(ev.arrays["episodes/seed"])
    return [float(hit[seeds == s].mean()) for s in dict.fromkeys(seeds.tolist())]


def body_text(rates: list[dict[str, list[float]] | None], seed: int | None = None, digits: int = 1) -> str | None:
    """Percent by body of :func:`body_crossing_rates` or :func:`body_state_rates`, e.g. ``gripper 12.0; block 30.0``:
    pooled over every seed of ``rates`` (one entry per eval), or of seed index ``seed`` of the one eval; None when
    any eval lacks them."""
    if not rates or any(r is None for r in rates):
        return None
    names = list(dict.fromkeys(n for r in rates for n in r))
    if seed is not None:
        return "; ".join(f"{n} {100 * rates[0][n][seed]:.{digits}f}" for n in names)
    pooled = {n: float(np.mean([x for r in rates for x in r.get(n, [])])) for n in names}
    return "; ".join(f"{n} {100 * v:.{digits}f}" for n, v in pooled.items())
