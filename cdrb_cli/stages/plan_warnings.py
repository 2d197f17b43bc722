"""The one-line warnings `cdrb plan` and `cdrb eval` give about plans a robot cannot follow: plans that leave their
start faster than the dynamics allow or pass through an obstacle, and plans that jump out of the scene."""

from __future__ import annotations

import numpy as np

from cdrb_cli.configs import AvoidConfig
from cdrb_cli.envs.registry import family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.stages.avoid import FIRST_STEP_TOLERANCE


def disconnected_warning(spec, plans: np.ndarray, stride: int, avoid: AvoidConfig | None = None) -> str | None:
    """One line when plans do not start where the robot is (a median first step over ``FIRST_STEP_TOLERANCE`` times
    what the dynamics allow in one plan step) or pass through an obstacle (a state in one, or a straight step
    between two states through one); None when neither. ``avoid``: the avoidance the plans were made with, for the
    advice in a changed scene. Longer steps later in a plan are normal (plans are paths
    the controller follows at its own pace) and not warned about."""
    family = family_of(spec)
    states = np.asarray(plans)[..., : spec.obs_dim].reshape(-1, plans.shape[-2], spec.obs_dim)
    problems = []
    crossing = np.asarray(family.path_in_collision(spec, states), dtype=bool)
    if crossing.any():
        problems.append(f"{int(crossing.sum())} of {len(states)} plans pass through an obstacle")
    allowed = family.plan_step_limit(spec, stride)
    if allowed is not None and states.shape[1] > 1:
        dims = list(spec.obstacles.dims)
        first = float(np.median(np.linalg.norm(states[:, 1, dims] - states[:, 0, dims], axis=-1)))
        if first > FIRST_STEP_TOLERANCE * allowed:
            problems.append(
                f"the first planned step is {first:.2f} (median), {first / allowed:.1f}x the {allowed:.2f} the "
                "dynamics allow in one plan step"
            )
    if not problems:
        return None
    apart = family.unconnected(spec, states[:, 0], states[:, -1])
    if apart is not None and apart.any():  # then no avoidance or data can help: say the cause
        return "; ".join(problems) + (
            f": {int(apart.sum())} of {len(states)} plans join a start and a goal that no free route connects in "
            f"{spec.id} (choose points in one connected region)"
        )
    if family.scene_changed(spec):
        if avoid is None or avoid.label() == "plain":
            advice = "`--set avoid=tuned` avoids the new obstacles with the settings chosen for them"
        else:
            advice = f"avoiding with {avoid.label()}; more: a larger avoid.best_of, or avoid.route_k"
        return "; ".join(problems) + (
            f" in a map the model was not trained in ({advice}; docs/design.md 'New obstacles without retraining')"
        )
    return (
        "; ".join(problems) + ": the start may lie where the training data never starts "
        "(`cdrb collect --starts anywhere`, docs/design.md 'Plans from anywhere')"
    )


def off_scene_warning(spec: EnvSpec, jumps, stride: int, avoid: AvoidConfig | None = None) -> str | None:
    """One line when a plan steps, between two consecutive planned states, farther than the whole scene is across
    (the diagonal of its workspace, :attr:`BoxObstacles.low` to ``high``): no robot follows such a plan, whatever
    success and the in-obstacle figures say (guidance at a large ``avoid.guide_scale`` throws plans kilometres
    away). ``jumps``: each plan's largest step (:func:`~cdrb_cli.envs.geometry.largest_jump`); None when no plan
    jumps that far. Steps longer than the dynamics allow yet inside the scene are normal (plans are paths the
    controller follows at its own pace) and not warned about."""
    jumps = np.asarray(jumps, dtype=np.float64).ravel()
    ob = spec.obstacles
    across = float(np.linalg.norm(np.asarray(ob.high, dtype=np.float64) - np.asarray(ob.low, dtype=np.float64)))
    far = np.isfinite(jumps) & (jumps > across)
    if not far.any():
        return None
    largest = float(jumps[far].max())
    allowed = family_of(spec).plan_step_limit(spec, stride)
    ratio = f", {largest / allowed:.3g}x the {allowed:.2f} m the dynamics allow in one plan step" if allowed else ""
    if avoid is not None and avoid.guide_scale > 0:
        advice = f"avoid.guide_scale={avoid.guide_scale:g} pushes plans out of the scene: lower it"
    else:
        advice = "the model's plans leave the scene: check the model and its settings"
    return (
        f"{int(far.sum())} of {len(jumps)} plans jump farther in one planned step than the scene is across "
        f"(up to {largest:.3g} m{ratio}; the scene is {across:.3g} m across): no robot can follow them, whatever "
        f"the success figures say ({advice})"
    )
