"""An eval's results as records: one :class:`EpisodeResult` per episode and the ``episodes/*`` datasets that store
them, the figures of one seed (:func:`seed_result`) and their summary over seeds (:func:`summarize`). What
`cdrb eval` writes and `cdrb report`, `cdrb select` and the logs read back."""

from __future__ import annotations

import typing
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cdrb_cli.artifacts.migrations import backfill_arrays
from cdrb_cli.configs import EvalSummary, SeedResult
from cdrb_cli.stages.metrics import failure_counts, mean_or_none, sample_std, std_or_none, sum_failures


@dataclass(frozen=True)
class EpisodeResult:
    """One evaluation episode, as stored in the eval artifact's ``episodes/*`` datasets."""

    seed: int
    episode_seed: int
    success: bool
    steps: int
    final_distance: float
    plan_in_wall_fraction: float
    plan_crosses_obstacle: bool
    plan_max_jump: float
    plan_step_limit: float
    executed_collision: bool
    path_length: float
    expert_path_length: float
    plan_seconds: float
    start: np.ndarray
    goal: np.ndarray
    replans: int = 0
    planning_seconds: float = 0.0
    failure: int = -1  # FAILURE_CODES


_DTYPES = {int: np.int64, float: np.float64, bool: np.bool_, np.ndarray: np.float32}


#: the per-episode fields that measure a plan (a policy's eval has none of them)
PLAN_FIELDS = ("plan_in_wall_fraction", "plan_crosses_obstacle", "plan_max_jump", "plan_step_limit")


def episode_arrays(results: Sequence[EpisodeResult], plans: bool = True) -> dict[str, np.ndarray]:
    """The ``episodes/<field>`` datasets of a list of results (one row per episode); without the plan measures
    when ``plans`` is false (a closed-loop policy)."""
    return {
        f"episodes/{name}": np.asarray([getattr(r, name) for r in results], dtype=_DTYPES[hint])
        for name, hint in typing.get_type_hints(EpisodeResult).items()
        if plans or name not in PLAN_FIELDS
    }


#: per-episode fields added in schema 2.2; an older file reads them as "not measured" (see :func:`measured`)
_SINCE_2_2 = {"plan_crosses_obstacle": False, "plan_max_jump": 0.0, "plan_step_limit": 0.0}


def episode_results(arrays: dict[str, np.ndarray]) -> list[EpisodeResult]:
    """The inverse of :func:`episode_arrays`: the records of an eval artifact's ``episodes/*`` datasets."""
    fields = list(typing.get_type_hints(EpisodeResult))
    n = len(arrays["episodes/seed"])
    cast = {np.ndarray: np.asarray, int: int, float: float, bool: bool}
    hints = typing.get_type_hints(EpisodeResult)
    # optional datasets a file left out read as what their absence means (artifacts.migrations); a plan measure
    # absent from a file is "not measured": a policy's eval, or an eval from before schema 2.2
    arrays = backfill_arrays("eval", arrays)
    cols = {f: arrays.get(f"episodes/{f}", np.full(n, _SINCE_2_2.get(f, np.nan))) for f in fields}
    return [EpisodeResult(**{f: cast[hints[f]](cols[f][i]) for f in fields}) for i in range(n)]


def measured(arrays: dict[str, np.ndarray]) -> bool:
    """Whether an eval's episodes carry the plan-crossing and jump measurements (schema 2.2 on)."""
    return all(f"episodes/{f}" in arrays for f in _SINCE_2_2)


def seed_result(seed: int, results: Sequence[EpisodeResult], policy: bool = False) -> SeedResult:
    succ = np.array([r.success for r in results])
    expert = np.array([r.expert_path_length for r in results])
    ratio = np.array([r.path_length for r in results]) / np.maximum(expert, 1e-9)
    measured = succ & (expert > 0)  # successful episodes with an expert reference
    limit = np.array([r.plan_step_limit for r in results])
    jump = np.array([r.plan_max_jump for r in results]) / np.maximum(limit, 1e-12)
    bounded = bool((limit > 0).all())
    failures = failure_counts([r.failure for r in results])
    clean = float(np.mean([r.success and not r.executed_collision for r in results]))
    if policy:  # no plans: nothing planned to measure
        return SeedResult(
            seed=int(seed),
            episodes=len(results),
            success_rate=float(succ.mean()),
            clean_success_rate=clean,
            in_wall_fraction=None,
            executed_collision_rate=float(np.mean([r.executed_collision for r in results])),
            path_length_ratio=float(ratio[measured].mean()) if measured.any() else None,
            plan_seconds=float(np.mean([r.plan_seconds for r in results])),
            planning_seconds=float(np.mean([r.planning_seconds for r in results])),
            failures=failures,
        )
    return SeedResult(
        seed=int(seed),
        episodes=len(results),
        success_rate=float(succ.mean()),
        weighted_success_rate=float(np.mean([r.success and r.plan_in_wall_fraction == 0 for r in results])),
        clean_success_rate=clean,
        in_wall_fraction=float(np.mean([r.plan_in_wall_fraction for r in results])),
        plan_crossing_rate=float(np.mean([r.plan_crosses_obstacle for r in results])),
        jump_ratio=float(jump.mean()) if bounded else None,
        impossible_jump_rate=float((jump > 1.0).mean()) if bounded else None,
        executed_collision_rate=float(np.mean([r.executed_collision for r in results])),
        path_length_ratio=float(ratio[measured].mean()) if measured.any() else None,
        plan_seconds=float(np.mean([r.plan_seconds for r in results])),
        replans=float(np.mean([r.replans for r in results])),
        planning_seconds=float(np.mean([r.planning_seconds for r in results])),
        failures=failures,
    )


def summarize(
    method: str,
    preset: str,
    per_seed: Sequence[SeedResult],
    wall_time_s: float,
    model_steps: int | None = None,
    model_training: str | None = None,
) -> EvalSummary:
    """Means and sample standard deviations over seeds of the per-seed results (``model_steps``: the training steps
    of the model evaluated; ``model_training``: the digest of its training settings)."""

    def mean(name):
        return mean_or_none(getattr(p, name) for p in per_seed)

    def std(name):
        return std_or_none(getattr(p, name) for p in per_seed)

    succ = [p.success_rate for p in per_seed]
    wall = [p.in_wall_fraction for p in per_seed]
    planned = all(w is not None for w in wall)
    ratios = [p.path_length_ratio for p in per_seed if p.path_length_ratio is not None]
    return EvalSummary(
        method=method,
        model_preset=preset,
        model_steps=model_steps,
        model_training=model_training,
        success_mean=float(np.mean(succ)),
        success_std=sample_std(succ),
        weighted_success_mean=mean("weighted_success_rate"),
        weighted_success_std=std("weighted_success_rate"),
        clean_success_mean=mean("clean_success_rate"),
        clean_success_std=std("clean_success_rate"),
        in_wall_mean=float(np.mean(wall)) if planned else None,
        in_wall_std=sample_std(wall) if planned else None,
        plan_crossing_mean=mean("plan_crossing_rate"),
        jump_ratio_mean=mean("jump_ratio"),
        impossible_jump_mean=mean("impossible_jump_rate"),
        executed_collision_mean=float(np.mean([p.executed_collision_rate for p in per_seed])),
        path_length_ratio_mean=float(np.mean(ratios)) if ratios else None,
        plan_seconds_mean=float(np.mean([p.plan_seconds for p in per_seed])),
        replans_mean=mean("replans"),
        planning_seconds_mean=mean("planning_seconds"),
        failures=sum_failures(p.failures for p in per_seed),
        per_seed=list(per_seed),
        wall_time_s=wall_time_s,
    )


def is_policy_eval(ev) -> bool:
    """Whether ``ev`` is a closed-loop policy's eval: no plans, so no plan measures and no controller."""
    return "episodes/plan_in_wall_fraction" not in ev.arrays


def per_seed(ev) -> list:
    """The per-seed results of an eval artifact, recomputed from its per-episode datasets (never taken from the
    manifest's summary, which a file may claim anything in)."""
    results = episode_results(ev.arrays)
    seeds = list(dict.fromkeys(r.seed for r in results))
    policy = is_policy_eval(ev)
    per = [seed_result(s, [r for r in results if r.seed == s], policy=policy) for s in seeds]
    if policy:
        return per
    if not measured(ev.arrays):  # an eval written before schema 2.2: crossings and jumps were not measured
        unknown = {"plan_crossing_rate": None, "jump_ratio": None, "impossible_jump_rate": None}
        per = [p.model_copy(update=unknown) for p in per]
    return per


def failure_text(counts: dict[str, int] | None) -> str | None:
    """``plan 2, grasp 0, collision 5, tracking 11``: failed episodes per cause (None: not classified)."""
    return None if counts is None else ", ".join(f"{cause} {n}" for cause, n in counts.items())
