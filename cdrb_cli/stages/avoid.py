"""What keeps a planner's plans out of obstacles it never saw in training: best-of-N samples judged by the scene's
collision test, and routes through the replay buffer that repairs start from (`cdrb plan`, `cdrb eval`, the API)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.configs import ROUTE_STEPS, AvoidConfig, MaskCounts
from cdrb_cli.envs.registry import family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.base import Planner
from cdrb_cli.stages.routes import BufferGraph

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
            raise BadInput(
                f"avoid.mask_buffer: {exc}: the new obstacles cover every state the robot visited",
                hint="plan without the mask (--set avoid.mask_buffer=false), or open part of the scene",
            ) from None
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
            f"avoid.route_buffer = {route_buffer.path}: a buffer of {env.id}, but the model plans in {task}",
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
