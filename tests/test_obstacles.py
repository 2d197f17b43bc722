"""New obstacles at plan and eval time, no retraining: the map check, the detour protocol, the masked buffer, best-of-N,
buffer routes and collision guidance."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.configs import AvoidConfig
from cdrb_cli.envs.pointmaze.maze import MazeGeometry
from cdrb_cli.envs.registry import family_of, make_spec
from cdrb_cli.errors import BadInput, NeedsScene

MAPS = Path(__file__).resolve().parent.parent / "experiments" / "maps"
NORTH = MAPS / "maze-tight-closed-north.txt"


def _rows(name: str = "maze-tight") -> list[str]:
    return list(make_spec(name).scene.maze.rows)


def _write(tmp_path, rows, name="new"):
    p = tmp_path / f"{name}.txt"
    p.write_text("\n".join(rows) + "\n")
    return p


# ------------------------------------------------------------------------------------------------ the map
def test_new_map_keeps_the_task_and_records_the_training_map():
    spec = make_spec("maze-tight")
    new = family_of(spec).with_map(spec, NORTH)
    assert new.id == "maze-tight+maze-tight-closed-north"
    assert new.scene.trained_maze == spec.scene.maze
    assert new.scene.maze.rows[4][7] == "#" and spec.scene.maze.rows[4][7] == "."
    assert (new.horizon, new.episode_limit, new.obs_dim) == (spec.horizon, spec.episode_limit, spec.obs_dim)
    # the gap's centre is free in training and in collision now
    gap = MazeGeometry(spec.scene.maze).cell_to_xy([4, 7])
    state = np.array([[*gap, 0, 0]])
    assert not family_of(spec).in_collision(spec, state)[0] and family_of(spec).in_collision(new, state)[0]
    assert family_of(spec).scene_change_warning(new) is None
    # a second change is made against the training map, not the first change
    again = family_of(spec).with_map(new, NORTH)
    assert again.id == new.id and again.scene.trained_maze == spec.scene.maze


def test_map_of_another_size_is_refused(tmp_path):
    spec = make_spec("maze-tight")
    small = _write(tmp_path, _rows("umaze"))
    with pytest.raises(BadInput, match=r"--maze-map .*a 5x5 map, but the model was trained in a 15x15 map"):
        family_of(spec).with_map(spec, small)


def test_map_that_opens_a_wall_warns(tmp_path):
    spec = make_spec("maze-tight")
    rows = _rows()
    rows[4] = rows[4][:5] + "." + rows[4][6:]  # open a wall cell of the inner ring
    new = family_of(spec).with_map(spec, _write(tmp_path, rows, "opened"))
    warning = family_of(spec).scene_change_warning(new)
    assert warning is not None and "1 cell(s) free here were walls in training ((4,5))" in warning


def test_detour_pairs_are_longer_in_the_new_map():
    spec = make_spec("maze-tight")
    family = family_of(spec)
    new = family.with_map(spec, NORTH)
    episodes = family.draw_protocol_episodes(new, 200, 3, 1, "detour")
    trained, here = MazeGeometry(spec.scene.maze), MazeGeometry(new.scene.maze)
    for ep in episodes:
        assert here.bfs(ep.goal)[ep.start] > trained.bfs(ep.goal)[ep.start] >= 0
    # every detour pair can come up, and only those
    assert {(e.start, e.goal) for e in episodes} <= {
        (tuple(p[:2]), tuple(p[2:])) for p in here.detour_pairs(trained).tolist()
    }
    assert len({e.goal for e in episodes}) == 2  # the two northern corners: the north gap leads only there


def test_detour_needs_a_map_that_lengthens_a_path(tmp_path):
    spec = make_spec("maze-tight")
    family = family_of(spec)
    with pytest.raises(BadInput, match="runs in the map it was trained in"):
        family.draw_protocol_episodes(spec, 3, 0, 1, "detour")
    same = family.with_map(spec, _write(tmp_path, _rows(), "same"))  # the training map again: no path is longer
    with pytest.raises(BadInput, match="lengthen no start-to-goal path"):
        family.draw_protocol_episodes(same, 3, 0, 1, "detour")


# ------------------------------------------------------------------------------------------------ the crossing test
def test_crossing_counts_count_steps_through_walls():
    spec = family_of(make_spec("maze-tight")).with_map(make_spec("maze-tight"), NORTH)
    family = family_of(spec)
    g = MazeGeometry(spec.scene.maze)
    inside, outside = g.cell_to_xy([5, 7]), g.cell_to_xy([3, 7])  # either side of the closed north gap
    jump = np.array([[*inside, 0, 0], [*outside, 0, 0], [*g.cell_to_xy([3, 6]), 0, 0]])
    stay = np.array([[*outside, 0, 0], [*g.cell_to_xy([3, 6]), 0, 0], [*g.cell_to_xy([2, 6]), 0, 0]])
    assert not family.in_collision(spec, jump).any()  # every state is free ...
    np.testing.assert_array_equal(family.crossing_counts(spec, np.stack([jump, stay])), [1, 0])  # ... one step is not
    assert family.path_in_collision(spec, jump[None])[0]


# ------------------------------------------------------------------------------------------------ best of N
def test_best_of_keeps_a_free_plan_then_the_shortest():
    from cdrb_cli.stages.avoid import Avoidance

    spec = family_of(make_spec("maze-tight")).with_map(make_spec("maze-tight"), NORTH)
    g = MazeGeometry(spec.scene.maze)
    a, b = g.cell_to_xy([5, 7]), g.cell_to_xy([3, 7])

    def plan(*cells):
        return np.array([[*g.cell_to_xy(c), 0, 0] for c in cells])

    through = np.array([[*a, 0, 0], [*b, 0, 0], [*b, 0, 0], [*b, 0, 0]])
    long_free = plan([5, 7], [6, 7], [7, 7], [7, 8])
    short_free = plan([5, 7], [6, 7], [6, 7], [6, 7])
    twice = np.array([[*a, 0, 0], [*b, 0, 0], [*a, 0, 0], [*b, 0, 0]])
    avoid = Avoidance(spec, best_of=3)
    plans = np.stack([through, long_free, short_free, twice, through, twice])
    np.testing.assert_array_equal(avoid.choose(plans), [2, 4])  # pair 1: the shorter free plan; pair 2: fewest


def test_best_of_prefers_a_plan_that_starts_where_the_robot_is():
    """With avoid.first_step, among plans that cross nothing one whose first step is within FIRST_STEP_TOLERANCE x
    the step limit is kept before a shorter one that leaps from its start; crossings still come first (a leap that
    stays clear beats a plan through a wall); without it the shortest clear plan is kept."""
    from cdrb_cli.stages.avoid import FIRST_STEP_TOLERANCE, Avoidance

    spec = family_of(make_spec("maze-tight")).with_map(make_spec("maze-tight"), NORTH)
    g = MazeGeometry(spec.scene.maze)
    a, b, c = (np.array([*g.cell_to_xy(cell), 0, 0]) for cell in ([5, 7], [6, 7], [3, 7]))
    limit = 0.2
    # a leap: the whole way in the first step, then standing at the end; a walk: small steps all the way, longer
    leap = np.stack([a, b, b, b, b, b])
    walk = np.stack([a + (b - a) * f for f in (0, 0.1, 0.3, 0.6, 1.0, 1.0)])
    walk[2:5, 1] += 0.3  # a detour: longer than the leap
    assert np.linalg.norm((leap[1] - leap[0])[:2]) > FIRST_STEP_TOLERANCE * limit
    assert np.linalg.norm((walk[1] - walk[0])[:2]) <= FIRST_STEP_TOLERANCE * limit
    through = np.stack([a, a + (c - a) * 0.05, c, c, c, c])  # a short first step, through the closed north gap
    plans = np.stack([leap, walk, leap, through])
    np.testing.assert_array_equal(Avoidance(spec, best_of=2, first_step=True, step_limit=limit).choose(plans), [1, 2])
    np.testing.assert_array_equal(Avoidance(spec, best_of=2, step_limit=limit).choose(plans), [0, 2])
    np.testing.assert_array_equal(Avoidance(spec, first_step=True, step_limit=limit).leaping(plans), [0, 2])
    assert not len(Avoidance(spec, step_limit=limit).leaping(plans))


# ------------------------------------------------------------------------------------------------ masking
def test_masked_buffer_never_restores_a_state_inside_the_new_wall(tiny_models):
    from cdrb_cli.stages.avoid import prepare_planner
    from cdrb_cli.stages.plan import load_planner, sample_plans

    model = tiny_models["cdrb"]
    spec = family_of(model.manifest.env).with_map(model.manifest.env, NORTH)
    family = family_of(spec)
    plain = load_planner(model)
    masked = load_planner(model)
    avoid = prepare_planner(masked, spec, AvoidConfig(mask_buffer=True))
    norm = masked.normalizer
    raw = norm.unnormalize(masked.points)
    removed = family.in_collision(spec, raw[:, :4])
    assert avoid.masked == {"buffer_states": len(raw), "removed": int(removed.sum())}
    # the sampler draws only from the kept states: the start of sampling and every degradation
    rng = np.random.default_rng(0)
    start = masked.ball.random_states((500,), rng)
    assert not family.in_collision(spec, norm.unnormalize(start)[:, :4]).any()
    # plans from the middle of the closed gap's cell: the untrained network restores states in the new wall,
    # and every one between the pinned ends is re-drawn from the kept buffer
    g = MazeGeometry(spec.scene.maze)
    gap = np.array([[*g.cell_to_xy([4, 7]) + [0.0, 0.45], 0, 0]] * 8)
    goals = family.goal_state(spec, np.array([[*g.cell_to_xy([1, 1])]] * 8))
    before = sample_plans(plain, gap, goals, 1, 0).plans
    after = sample_plans(masked, gap, goals, 1, 0, avoid=avoid).plans
    inner = lambda p: family.in_collision(spec, p[:, 1:-1, :4])  # noqa: E731
    assert masked.redrawn > 0 and masked.unreachable == 0  # the re-draw was needed, and always found a state
    assert not inner(after).any()
    assert before.shape == after.shape


def test_replans_in_a_new_map_keep_the_masked_buffer_and_the_best_of(tiny_models):
    """Closed loop among new walls: every re-plan comes from the masked buffer and the best-of choice, as the
    first plan does (a re-plan from where the robot got stuck must not walk back into the new wall)."""
    from cdrb_cli.configs import ReplanConfig
    from cdrb_cli.envs.pointmaze.controllers import CONTROLLERS
    from cdrb_cli.stages.avoid import prepare_planner
    from cdrb_cli.stages.plan import load_planner, sample_plans
    from cdrb_cli.stages.replan import run_closed_loop

    model = tiny_models["cdrb"]
    spec = family_of(model.manifest.env).with_map(model.manifest.env, NORTH)
    family = family_of(spec)
    method = load_planner(model)
    avoid = prepare_planner(method, spec, AvoidConfig(mask_buffer=True, best_of=2))
    episodes = family.draw_protocol_episodes(spec, 3, 0, 1, "detour")
    starts, goals = family.reset_states(spec, episodes)
    first = sample_plans(method, starts, family.goal_state(spec, goals), 1, 0, avoid=avoid).plans
    entry = CONTROLLERS.get("pd")
    runs = run_closed_loop(
        family,
        spec,
        method,
        episodes,
        first,
        lambda env: entry.build(spec, env, entry.config(), method.config.stride),
        ReplanConfig(mode="every", every=15),
        60,
        (0, 0, 0),
        avoid=avoid,
    )
    replans = [p for run in runs for p in run.plans[1:]]
    assert len(replans) >= 3  # each episode planned again at least once
    inner = np.stack([p[1:-1, :4] for p in replans])
    assert not family.in_collision(spec, inner).any()
    assert method.redrawn > 0  # the untrained network restored states in walls: the masked buffer re-drew them


def test_mask_and_route_refused_where_they_do_not_apply(tiny_models, cdrb, tmp_path):
    out = tmp_path / "e.h5"

    def refused(model, *args):
        r = cdrb("eval", tiny_models[model].path, "-n", "2", "--seeds", "0", "--out", out, *args)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        return r.stderr

    assert "--set avoid.mask_buffer=true: diffuser samples from no replay buffer" in refused(
        "diffuser", "--set", "avoid.mask_buffer=true"
    )
    assert "--set avoid.guide_scale=0.1: cdrb has no guided sampling" in refused(
        "cdrb", "--set", "avoid.guide_scale=0.1"
    )
    assert "--set avoid.route_k=2: mlp cannot restore" in refused("mlp", "--set", "avoid.route_k=2")
    assert "add avoid.route_buffer=" in refused("diffuser", "--set", "avoid.route_k=2")
    assert "route_clearance keeps routes clear of obstacles: set route_k or fallback_route_k too" in refused(
        "cdrb", "--set", "avoid.route_clearance=0.1"
    )
    # the moved flags still work, with a note naming the setting
    r = cdrb("eval", tiny_models["diffuser"].path, "--mask-buffer", "-n", "2", "--seeds", "0", "--out", out)
    assert r.returncode == 2 and "--mask-buffer is deprecated: write --set avoid.mask_buffer=true" in r.stderr
    assert "--mask-buffer: diffuser samples from no replay buffer" in r.stderr
    r = cdrb("eval", tiny_models["cdrb"].path, "--protocol", "detour", "-n", "2", "--seeds", "0", "--out", out)
    assert r.returncode == 2 and "(give the training map with walls added: --maze-map FILE)" in r.stderr
    assert not out.exists() and len(r.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------------ routes
def _north_closed_buffer():
    """Maze Tight with its north gap closed, its geometry, and buffer states at rest: three jittered points in every
    free cell, those in a wall dropped."""
    base = make_spec("maze-tight")
    spec = family_of(base).with_map(base, NORTH)
    g = MazeGeometry(spec.scene.maze)
    free = np.argwhere(g.free)
    rng = np.random.default_rng(0)
    xy = np.concatenate([g.cell_to_xy(free) + rng.uniform(-0.3, 0.3, (len(free), 2)) for _ in range(3)])
    states = np.concatenate([xy, np.zeros((len(xy), 2))], 1)
    return spec, g, states[~family_of(spec).in_collision(spec, states)]


def test_buffer_route_takes_free_steps_around_the_new_wall():
    from cdrb_cli.stages.routes import BufferGraph

    spec, g, states = _north_closed_buffer()
    family = family_of(spec)
    graph = BufferGraph(spec, states)
    start, goal = np.array([*g.cell_to_xy([5, 7]), 0, 0]), np.array([*g.cell_to_xy([1, 6]), 0, 0])
    route = graph.route(start, goal, 64)
    assert route.shape == (64, 4)
    np.testing.assert_array_equal(route[0], start)
    np.testing.assert_array_equal(route[-1], goal)
    assert family.crossing_counts(spec, route) == 0
    # it goes round: through the west or east gap, far longer than the straight line through the closed gap
    length = np.linalg.norm(np.diff(route[:, :2], axis=0), axis=1).sum()
    assert length > 2 * np.linalg.norm(goal[:2] - start[:2])
    # a goal that no buffer state reaches by a free step has no route (here: a buffer of the centre region only)
    cells = g.xy_to_cell(states[:, :2])
    centre = states[(cells[:, 0] >= 5) & (cells[:, 0] <= 9) & (cells[:, 1] >= 5) & (cells[:, 1] <= 9)]
    assert BufferGraph(spec, centre).route(start, goal, 64) is None


def test_a_waypoint_lies_reach_along_the_route_and_is_the_goal_once_the_route_is_short():
    """``BufferGraph.waypoint``: the point ``reach`` along the shortest route by arc length (so on the route, within
    ``reach`` of the start as the crow flies, and joined to the start by free steps), the goal itself once the route
    is no longer than ``reach``; ``waypoint_aims`` gives it as a goal state (at rest)."""
    from cdrb_cli.stages.routes import BufferGraph, waypoint_aims

    spec, g, states = _north_closed_buffer()
    family = family_of(spec)
    graph = BufferGraph(spec, states)
    start, goal = np.array([*g.cell_to_xy([5, 7]), 0.4, -0.2]), np.array([*g.cell_to_xy([1, 6]), 0, 0])
    points = graph.polyline(start, goal)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1))])
    for reach in (0.5, 2.0, 0.4 * arc[-1]):
        point = graph.waypoint(start, goal, reach)
        i = int(np.searchsorted(arc, reach)) - 1
        a, b = points[i, :2], points[i + 1, :2]
        # on the segment that holds arc length ``reach``, at that arc length
        assert np.isclose(arc[i] + np.linalg.norm(point[:2] - a), reach)
        assert np.isclose(np.linalg.norm(point[:2] - a) + np.linalg.norm(b - point[:2]), np.linalg.norm(b - a))
        assert np.linalg.norm(point[:2] - start[:2]) <= reach + 1e-9
        walked = np.concatenate([points[: i + 1, :2], point[None, :2]])[None]
        assert not family.path_in_collision(spec, np.concatenate([walked, np.zeros_like(walked)], -1))[0]
    np.testing.assert_array_equal(graph.waypoint(start, goal, arc[-1] + 0.1), goal)
    aims = waypoint_aims(graph, spec, 2.0, features=4)
    out = aims(np.stack([start, goal]), np.stack([goal, goal]))
    np.testing.assert_allclose(out[0, :2], graph.waypoint(start, goal, 2.0)[:2])
    assert (out[0, 2:] == 0).all()  # a goal state: at rest
    np.testing.assert_array_equal(out[1], goal)  # already there: the goal itself


def test_transition_routes_follow_what_the_demonstrations_joined():
    """Routes along the transition graph go only where consecutive buffer states were joined (no map read): a
    chain of states around a wall is followed even though the straight step would be shorter; states no edge joins
    have no route; a waypoint lies the reach along the chain."""
    from cdrb_cli.stages.routes import TransitionRoutes

    spec = family_of(make_spec("maze-tight")).with_map(make_spec("maze-tight"), NORTH)
    xy = np.array([[0.0, 0.0], [0.0, 2.0], [2.0, 2.0], [2.0, 0.0], [5.0, 5.0]])  # a U, and one state apart
    states = np.concatenate([xy, np.zeros((5, 2))], 1)
    routes = TransitionRoutes(spec, states, np.array([[0, 1], [1, 2], [2, 3]]))
    line = routes.polyline(states[0] + [0.1, 0, 0, 0], states[3] + [-0.1, 0, 0, 0])
    np.testing.assert_allclose(line[1:-1, :2], xy[:4])  # round the U, not straight across
    assert routes.polyline(states[0], states[4]) is None  # nothing joins the lone state
    np.testing.assert_allclose(routes.waypoint(states[0], states[3], 3.0)[:2], [1.0, 2.0])
    np.testing.assert_array_equal(routes.waypoint(states[0], states[3], 6.0), states[3])


class _LinePlanner:
    """A stand-in planner for the sampler's plumbing: from scratch it plans the straight line (through any wall in
    the way), a repair gives back the plan it was given (the buffer route), so what the second try changes is
    visible."""

    obs_dim = feature_dim = 4
    horizon = 48
    pinned = pinned_end = slice(0, 4)

    def __init__(self):
        from cdrb_cli.buffer import Normalizer

        self.normalizer = Normalizer(low=np.full(4, -8.0, np.float32), high=np.full(4, 8.0, np.float32))
        self.repairs_from = []

    def sample(self, start, goal, rng, sampler=None, steps=None, keep_iterates=0):
        import torch

        from cdrb_cli.methods.base import SampleResult

        w = torch.linspace(0, 1, self.horizon)[None, :, None]
        return SampleResult(plans=start[:, None] * (1 - w) + goal[:, None] * w)

    def repair(self, start, goal, previous, k, rng, sampler=None, steps=None):
        from cdrb_cli.methods.base import SampleResult

        self.repairs_from.append(k)
        return SampleResult(plans=previous.clone())


def test_a_pair_whose_every_plan_crosses_is_tried_again_from_a_buffer_route():
    """``avoid.fallback_route_k``: only the pairs whose kept plan steps through a wall are sampled again, as repairs
    of their buffer route from step k, and the better plan is kept; a pair whose plan is clear is left alone."""
    from cdrb_cli.stages.avoid import Avoidance
    from cdrb_cli.stages.plan import sample_plans
    from cdrb_cli.stages.routes import BufferGraph

    spec, g, states = _north_closed_buffer()
    family = family_of(spec)
    at = lambda cell: np.array([*g.cell_to_xy(cell), 0.0, 0.0])  # noqa: E731
    starts = np.stack([at([5, 7]), at([1, 1])])  # through the closed north gap; along a free corridor
    goals = np.stack([at([1, 6]), at([1, 3])])
    lines = sample_plans(_LinePlanner(), starts, goals, 1, 0, avoid=Avoidance(spec, best_of=2)).plans
    before = family.crossing_counts(spec, lines)
    assert before[0] > 0 and before[1] == 0

    method = _LinePlanner()
    avoid = Avoidance(spec, best_of=2, graph=BufferGraph(spec, states), fallback_route_k=3)
    plans = sample_plans(method, starts, goals, 1, 0, avoid=avoid).plans
    assert avoid.rerouted == 1 and method.repairs_from == [3]  # one pair, tried again from k = 3
    assert list(family.crossing_counts(spec, plans)) == [0, 0]
    np.testing.assert_allclose(plans[1], lines[1])  # the clear pair keeps its plan
    np.testing.assert_allclose(plans[:, 0], starts)
    np.testing.assert_allclose(plans[:, -1], goals)


class _LeapingPlanner(_LinePlanner):
    """A stand-in whose plans from scratch leave the start at once (the first step goes half the way)."""

    def sample(self, start, goal, rng, sampler=None, steps=None, keep_iterates=0):
        import torch

        from cdrb_cli.methods.base import SampleResult

        w = torch.full((self.horizon,), 0.5)
        w[0], w[-1] = 0.0, 1.0
        w = w[None, :, None]
        return SampleResult(plans=start[:, None] * (1 - w) + goal[:, None] * w)


def test_a_pair_whose_every_plan_leaps_from_its_start_is_tried_again():
    """A clear plan whose first step goes farther than FIRST_STEP_TOLERANCE x the step limit also gets the second
    try: the repair of its buffer route (which walks from the start) is kept instead; a pair whose plan starts
    gently is left alone."""
    from cdrb_cli.stages.avoid import Avoidance
    from cdrb_cli.stages.plan import sample_plans
    from cdrb_cli.stages.routes import BufferGraph

    spec, g, states = _north_closed_buffer()
    at = lambda cell: np.array([*g.cell_to_xy(cell), 0.0, 0.0])  # noqa: E731
    starts, goals = np.stack([at([1, 1]), at([1, 1])]), np.stack([at([1, 3]), at([1, 1]) + [0.05, 0, 0, 0]])
    method = _LeapingPlanner()
    limit = 2 * np.linalg.norm(goals[0, :2] - starts[0, :2]) / method.horizon  # the route's steps fit; a leap not
    avoid = Avoidance(
        spec, best_of=2, graph=BufferGraph(spec, states), fallback_route_k=3, first_step=True, step_limit=limit
    )
    plans = sample_plans(method, starts, goals, 1, 0, avoid=avoid).plans
    assert avoid.rerouted == 1 and method.repairs_from == [3]
    first = np.linalg.norm(plans[:, 1, :2] - plans[:, 0, :2], axis=1)
    assert first[0] <= 1.5 * limit
    np.testing.assert_allclose(plans[:, 0], starts)
    np.testing.assert_allclose(plans[:, -1], goals)


def _on_polyline(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Per point (n, 2): its distance to the polyline ``path`` (m, 2)."""
    a, b = path[:-1], path[1:]
    d = b - a
    t = np.clip(((points[:, None] - a[None]) * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-12)[None], 0, 1)
    return np.linalg.norm(points[:, None] - (a[None] + t[..., None] * d[None]), axis=-1).min(axis=1)


def test_a_plan_that_still_leaps_is_retimed_along_its_own_path():
    """``avoid.retime``: a clear kept plan whose first step leaps is respaced evenly by arc length along its own path:
    the first step within the tolerance, the ends exactly where they were, every state on the plan's own steps, still
    clear; a plan that starts gently is left alone, so is one through an obstacle (respaced, more of its states could
    fall in the wall), one whose path is too long to respace within the tolerance, and nothing changes without the
    setting. Through the sampler the normalized plans follow."""
    from cdrb_cli.stages.avoid import FIRST_STEP_TOLERANCE, Avoidance
    from cdrb_cli.stages.plan import _sampler_call, sample_plans

    spec, g, _ = _north_closed_buffer()
    family = family_of(spec)
    at = lambda cell: np.array([*g.cell_to_xy(cell), 0.0, 0.0])  # noqa: E731
    a, b, c = at([5, 7]), at([6, 7]), at([3, 7])
    H, limit = 12, 0.25
    leap = np.stack([a, *(b for _ in range(H - 1))])  # the whole way at once, then standing
    walk = np.stack([a + (b - a) * f for f in np.linspace(0, 1, H)])
    through = np.stack([a, c, *(c for _ in range(H - 2))])  # a leap through the closed north gap
    far = np.stack([a, *(a + [40.0, 0, 0, 0] for _ in range(H - 1))])  # too far for H steps at any pace
    plans = np.stack([leap, walk, through, far])
    avoid = Avoidance(spec, retime=True, step_limit=limit)
    out, rows = avoid.retimed_plans(plans)
    np.testing.assert_array_equal(rows, [0])
    assert avoid.retimed == 1
    for i in (1, 2, 3):
        np.testing.assert_array_equal(out[i], plans[i])
    for i in rows:
        steps = np.linalg.norm(np.diff(out[i][:, :2], axis=0), axis=1)
        assert steps[0] <= FIRST_STEP_TOLERANCE * limit and np.ptp(steps) < 1e-9  # evenly spaced
        np.testing.assert_array_equal(out[i][[0, -1]], plans[i][[0, -1]])
        assert _on_polyline(out[i][:, :2], plans[i][:, :2]).max() < 1e-9
    counts = family.crossing_counts(spec, plans[..., : spec.obs_dim])
    np.testing.assert_array_equal(family.crossing_counts(spec, out[..., : spec.obs_dim]), counts)
    assert counts[0] == 0 and counts[2] > 0
    same, none = Avoidance(spec, step_limit=limit).retimed_plans(plans)
    assert same is plans and not len(none)
    # through the sampler: the leaping stand-in's plan is retimed, in raw units and in the normalized result
    method = _LeapingPlanner()
    start, goal = at([1, 1])[None], at([1, 3])[None]
    gentle = 1.2 * np.linalg.norm(goal[0, :2] - start[0, :2]) / (method.horizon - 1)
    avoid = Avoidance(spec, retime=True, step_limit=gentle)
    sampled = sample_plans(method, start, goal, 1, 0, avoid=avoid).plans
    assert avoid.retimed == 1
    first = np.linalg.norm(sampled[0, 1, :2] - sampled[0, 0, :2])
    assert first <= FIRST_STEP_TOLERANCE * gentle
    np.testing.assert_allclose(sampled[0, [0, -1]], np.concatenate([start, goal]))
    out, res, _ = _sampler_call(method, start, goal, np.random.default_rng(0), None, None, avoid=avoid)
    np.testing.assert_allclose(method.normalizer.unnormalize(res.plans.numpy().astype(np.float64)), out, atol=1e-5)


class _StubbornPlanner(_LinePlanner):
    """A stand-in whose repairs cross too: every repair is the straight line again, whatever route it was given."""

    def repair(self, start, goal, previous, k, rng, sampler=None, steps=None):
        self.repairs_from.append(k)
        return self.sample(start, goal, rng)


@pytest.mark.parametrize(("itself", "pinned"), [(False, slice(0, 4)), (True, slice(0, 4)), (True, [0, 1, 2, 3])])
def test_a_pair_whose_every_repair_crosses_may_keep_the_route_itself(itself, pinned):
    """``avoid.fallback_route_itself``: when the repairs of the second try cross as well, the buffer route itself
    (free by construction here) replaces the kept plan, pinned to the pair and normalized in the sampler's result
    too; without it the crossing plan stays."""
    from cdrb_cli.stages.avoid import Avoidance
    from cdrb_cli.stages.plan import _sampler_call
    from cdrb_cli.stages.routes import BufferGraph

    spec, g, states = _north_closed_buffer()
    family = family_of(spec)
    at = lambda cell: np.array([*g.cell_to_xy(cell), 0.0, 0.0])  # noqa: E731
    # a clear pair first, then two through the closed north gap (pinned dims given as a slice or as a list)
    starts = np.stack([at([1, 1]), at([5, 7]), at([5, 6])])
    goals = np.stack([at([1, 3]), at([1, 6]), at([1, 7])])
    method = _StubbornPlanner()
    method.pinned = method.pinned_end = pinned
    graph = BufferGraph(spec, states)
    avoid = Avoidance(spec, best_of=2, graph=graph, fallback_route_k=3, fallback_route_itself=itself)
    plans, res, _ = _sampler_call(method, starts, goals, np.random.default_rng(0), None, None, avoid=avoid)
    assert avoid.rerouted == 2 and method.repairs_from == [3]
    assert avoid.route_kept == 2 * int(itself)
    crossings = list(family.crossing_counts(spec, plans))
    assert crossings[0] == 0 and all((c == 0) == itself for c in crossings[1:])
    if itself:
        for i in (1, 2):
            np.testing.assert_allclose(plans[i], graph.route(starts[i], goals[i], method.horizon))
        np.testing.assert_allclose(method.normalizer.unnormalize(res.plans.numpy()), plans, atol=1e-5)
    np.testing.assert_allclose(plans[:, 0], starts)
    np.testing.assert_allclose(plans[:, -1], goals)


def test_the_route_itself_needs_the_second_try():
    from cdrb_cli.configs import AvoidConfig

    with pytest.raises(ValueError, match="fallback_route_itself keeps the second try's route: set fallback_route_k"):
        AvoidConfig(fallback_route_itself=True)
    label = AvoidConfig(fallback_route_k=8, fallback_route_itself=True).label()
    assert label.endswith("the route itself as a last resort")


def test_route_clearance_keeps_routes_off_the_walls_where_the_buffer_allows():
    from cdrb_cli.stages.routes import BufferGraph

    base = make_spec("maze-tight")
    spec = family_of(base).with_map(base, NORTH)
    family = family_of(spec)
    g = MazeGeometry(spec.scene.maze)
    rng = np.random.default_rng(1)
    free = np.argwhere(g.free)
    xy = np.concatenate([g.cell_to_xy(free) + rng.uniform(-0.45, 0.45, (len(free), 2)) for _ in range(4)])
    states = np.concatenate([xy, np.zeros((len(xy), 2))], 1)
    states = states[~family.in_collision(spec, states)]
    start, goal = np.array([*g.cell_to_xy([5, 7]), 0, 0]), np.array([*g.cell_to_xy([1, 6]), 0, 0])
    clearance = 0.3
    near = BufferGraph(spec, states, clearance=clearance).near
    # "near" is its definition: a state that collides when moved the clearance along x or y
    probes = [states + s * clearance * np.eye(4)[d] for d in (0, 1) for s in (-1, 1)]
    assert all(near[family.in_collision(spec, q)].all() for q in probes) and near.any() and not near.all()

    def share_near(route):
        moved = [route + s * np.eye(4)[d] * clearance for d in (0, 1) for s in (-1, 1)]
        return np.mean(np.any([family.in_collision(spec, m) for m in moved], axis=0))

    plain = BufferGraph(spec, states).route(start, goal, 128)
    kept = BufferGraph(spec, states, clearance=clearance).route(start, goal, 128)
    assert family.crossing_counts(spec, kept) == 0
    assert share_near(kept) < share_near(plain)


# ------------------------------------------------------------------------------------------------ guidance
def test_collision_cost_gradient_moves_a_state_out_of_the_wall():
    import torch

    base = make_spec("maze-tight")
    spec = family_of(base).with_map(base, NORTH)
    cost = family_of(spec).collision_cost(spec)
    g = MazeGeometry(spec.scene.maze)
    x = torch.tensor([[*g.cell_to_xy([4, 7]) + [0.1, 0.32], 0.0, 0.0]], requires_grad=True)
    c = cost(x).sum()
    assert float(c.detach()) > 0
    (grad,) = torch.autograd.grad(c, x)
    y = x.detach().clone()
    for _ in range(50):
        y.requires_grad_(True)
        (gy,) = torch.autograd.grad(cost(y).sum(), y)
        y = (y - 0.05 * gy).detach()
    assert float(cost(y).sum()) == 0.0
    assert float(grad[0, 1]) < 0  # out through the nearer (north) face: y grows
    assert not family_of(spec).in_collision(spec, y.numpy())[0]


# ------------------------------------------------------------------------------------------------ end to end
def test_eval_in_a_new_map_end_to_end(tiny_models, small_data, cdrb, tmp_path):
    _, buffer = small_data
    out = tmp_path / "e.h5"
    args = ["--maze-map", NORTH, "--protocol", "detour", "-n", "4", "--seeds", "0", "--stream", "tune"]
    r = cdrb("eval", tiny_models["cdrb"].path, *args, "--mask-buffer", "--best-of", "2", "--route-k", "2", "--out", out)
    assert r.returncode == 0, r.stderr
    ev = artifacts.load(out, "eval")
    assert ev.manifest.env.id == "maze-tight+maze-tight-closed-north"
    assert ev.manifest.env.scene.trained_maze == tiny_models["cdrb"].manifest.env.scene.maze
    assert ev.manifest.config.scene == NORTH.name
    assert ev.manifest.config.avoid == AvoidConfig(mask_buffer=True, best_of=2, route_k=2)
    assert ev.manifest.summary.masked is not None and ev.manifest.summary.masked.removed >= 0
    # the report's "through a new wall" column: the plans' crossings of the closed gap's cells, by definition
    from cdrb_cli.stages.report import collect_rows, new_crossing_rates

    spec = ev.manifest.env
    gap = MazeGeometry(spec.scene.maze).cell_to_xy([4, 7])
    plans = ev.arrays["plans"][..., : spec.obs_dim]
    near = np.linalg.norm(plans[..., :2] - gap, axis=-1).min(-1) < 0.2  # a state within the gap cell's box
    rates = new_crossing_rates(ev)
    assert rates is not None and (near.mean() <= rates[0] + 1e-9)
    assert collect_rows([ev])[0]["new_crossing_mean"] == pytest.approx(100 * rates[0])
    # the second run is up to date; another map is a different eval
    r = cdrb("eval", tiny_models["cdrb"].path, *args, "--mask-buffer", "--best-of", "2", "--route-k", "2", "--out", out)
    assert r.returncode == 0 and "up to date" in r.stderr
    # Diffuser routed through a buffer artifact: the buffer is a parent
    d_out = tmp_path / "d.h5"
    r = cdrb(
        "eval", tiny_models["diffuser"].path, *args, "--route-k", "2", "--route-buffer", buffer.path, "--out", d_out
    )
    assert r.returncode == 0, r.stderr
    parents = artifacts.load(d_out, "eval").manifest.parents
    assert [p.kind for p in parents] == ["model", "buffer"] and parents[1].sha256 == buffer.sha256


def test_api_plans_in_a_new_map(tiny_models):
    from cdrb_cli import api

    planner = api.Planner(tiny_models["cdrb"].path, scene=NORTH, mask_buffer=True, best_of=2, route_k=2)
    assert planner.spec.id == "maze-tight+maze-tight-closed-north"
    g = MazeGeometry(planner.spec.scene.maze)
    plans = planner.plan(start=g.cell_to_xy([5, 7]), goal=g.cell_to_xy([1, 1]), n=3, seed=0)
    assert plans.states.shape[0] == 3
    assert not family_of(planner.spec).in_collision(planner.spec, plans.states[:, 1:-1]).any()
    with pytest.raises(BadInput, match="inside a wall"):  # the closed gap is a wall now
        planner.plan(start=g.cell_to_xy([4, 7]), goal=g.cell_to_xy([1, 1]))


def test_pairs_without_a_buffer_route_are_said(tiny_models, capsys):
    """A start the buffer cannot reach by a free step gets the straight line, and the count is reported."""
    from cdrb_cli.stages.avoid import prepare_planner, warn_unrouted
    from cdrb_cli.stages.plan import load_planner, sample_plans

    model = tiny_models["cdrb"]
    spec = family_of(model.manifest.env).with_map(model.manifest.env, NORTH)
    method = load_planner(model)
    from cdrb_cli.stages.routes import BufferGraph

    avoid = prepare_planner(method, spec, AvoidConfig(mask_buffer=True, route_k=2))
    g = MazeGeometry(spec.scene.maze)
    states = avoid.graph.states
    cells = g.xy_to_cell(states[:, :2])
    centre = (cells[:, 0] >= 5) & (cells[:, 0] <= 9) & (cells[:, 1] >= 5) & (cells[:, 1] <= 9)
    avoid.graph = BufferGraph(spec, states[centre])  # only the centre region's states: no way out to a corner
    start = np.array([[*g.cell_to_xy([5, 7]), 0, 0]])
    goal = family_of(spec).goal_state(spec, np.array([g.cell_to_xy([1, 1])]))
    sample_plans(method, start, goal, 1, 0, avoid=avoid)
    assert avoid.unrouted == 1
    warn_unrouted(avoid)
    assert "no route through the buffer joined 1 start/goal pair(s)" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------ Fetch: boxes put down
SCENES = Path(__file__).resolve().parent.parent / "experiments" / "scenes"
X_PLUS = SCENES / "reach-closed-x-plus.toml"


def _scene_file(tmp_path, text, name="box"):
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return p


def test_fetch_scene_file_puts_boxes_down_and_keeps_the_task():
    from cdrb_cli.envs.fetch.tasks import side

    spec = make_spec("fetch-reach-obstacle")
    fam = family_of(spec)
    new = fam.with_map(spec, X_PLUS)
    assert new.id == "fetch-reach-obstacle+reach-closed-x-plus" and fam.scene_changed(new)
    assert new.scene.walls == spec.scene.walls and len(new.scene.extra_boxes) == 1 and not fam.scene_changed(spec)
    # the corridor's x+ exit: free in training, in the board now (the gripper link is 4.7 cm ahead of the grip site)
    exit_ = np.zeros(spec.obs_dim)
    exit_[:3] = (1.42, 0.749, 0.55)
    assert not fam.in_collision(spec, exit_[None])[0] and fam.in_collision(new, exit_[None])[0]
    # a step out of the corridor through the exit crosses the board only in the new scene
    out = exit_.copy()
    out[0] = 1.56
    path = np.stack([exit_ - np.r_[0.1, np.zeros(spec.obs_dim - 1)], out])[None]
    assert not fam.path_in_collision(spec, path)[0] and fam.path_in_collision(new, path)[0]
    assert side(new.scene, np.array([1.3, 0.95, 0.5])) == side(spec.scene, np.array([1.3, 0.95, 0.5])) == 1
    again = fam.with_map(new, X_PLUS)  # a second change replaces the first
    assert again.id == new.id and again.scene.extra_boxes == new.scene.extra_boxes


def test_new_obstacle_crossings_count_only_the_new_obstacles():
    spec = make_spec("fetch-reach-obstacle")
    fam = family_of(spec)
    new = fam.with_map(spec, X_PLUS)
    assert fam.new_obstacle_crossings(spec, np.zeros((1, 2, spec.obs_dim))) is None  # the training scene
    a, b, c = (np.zeros(spec.obs_dim) for _ in range(3))
    a[:3], b[:3], c[:3] = (1.30, 0.749, 0.55), (1.56, 0.749, 0.55), (1.30, 0.50, 0.55)
    through_board, through_wall = np.stack([a, b]), np.stack([a, c])
    out_of_reach = np.stack([a, a + np.r_[0, 0, 1.0, np.zeros(spec.obs_dim - 3)]])  # above the workspace
    paths = np.stack([through_board, through_wall, out_of_reach])
    assert fam.path_in_collision(new, paths).tolist() == [True, True, True]
    assert fam.new_obstacle_crossings(new, paths).tolist() == [True, False, False]
    maze = make_spec("maze-tight")
    closed = family_of(maze).with_map(maze, NORTH)
    g = MazeGeometry(closed.scene.maze)
    across_gap = np.array([[[*g.cell_to_xy([5, 7]), 0, 0], [*g.cell_to_xy([3, 7]), 0, 0]]])
    across_old = np.array([[[*g.cell_to_xy([5, 6]), 0, 0], [*g.cell_to_xy([3, 6]), 0, 0]]])  # an old wall cell
    assert family_of(maze).path_in_collision(closed, np.concatenate([across_gap, across_old])).all()
    assert family_of(maze).new_obstacle_crossings(closed, np.concatenate([across_gap, across_old])).tolist() == [
        True,
        False,
    ]


def test_fetch_boxes_are_physics():
    """Driving the gripper out of the corridor's x+ end: it leaves in training, the board stops it in the new scene."""
    spec = make_spec("fetch-reach-obstacle")
    fam = family_of(spec)
    board_x = 1.45
    for scene, passes in ((spec, True), (fam.with_map(spec, X_PLUS), False)):
        env = fam.make_env(scene)
        try:
            env.reset(fam.draw_episodes(scene, 1, 0, 1)[0])
            for _ in range(20):
                s = env.step(np.array([1.0, 0.0, 0.0, 0.0]))
        finally:
            env.close()
        assert (s[0] > board_x + 0.05) == passes, s[:3]


def test_fetch_detour_pairs_have_their_shortest_route_blocked():
    from cdrb_cli.envs.fetch.expert import FetchExpertConfig, routers
    from cdrb_cli.envs.fetch.geometry import gripper_obstacles
    from cdrb_cli.envs.geometry import in_boxes

    spec = make_spec("fetch-reach-obstacle")
    fam = family_of(spec)
    new = fam.with_map(spec, X_PLUS)
    episodes = fam.draw_protocol_episodes(new, 30, 5, 1, "detour")
    assert len(episodes) == 30 and len({e.seed for e in episodes}) == 30
    assert [e.seed for e in fam.draw_protocol_episodes(new, 10, 5, 1, "detour")] == [e.seed for e in episodes[:10]]
    trained = routers(spec.scene, spec.scene.walls, FetchExpertConfig())[0]
    home = np.asarray(spec.scene.home)
    board = gripper_obstacles(new.scene.extra_boxes)
    for ep in episodes:
        goal = np.asarray(ep.goal)
        ways = trained.options(home, goal, ["over", "around"])
        shortest = min(ways, key=lambda k: np.linalg.norm(np.diff([home, *ways[k]], axis=0), axis=1).sum())
        assert shortest == "around x+"  # the one route the board closes
        assert not in_boxes(goal, board)
    # the stock draws hold pairs the board does not block: the protocol is a filter, not the stream
    stock = {e.seed for e in fam.draw_episodes(new, 40, 5, 1)}
    assert not stock <= {e.seed for e in fam.draw_protocol_episodes(new, 40, 5, 1, "detour")}


def test_fetch_detour_needs_boxes_that_block_a_route(tmp_path):
    spec = make_spec("fetch-reach-obstacle")
    fam = family_of(spec)
    with pytest.raises(NeedsScene, match="runs in the scene it was trained in") as err:
        fam.draw_protocol_episodes(spec, 3, 0, 1, "detour")
    assert err.value.hint == "give a TOML file of the boxes put down: --scene FILE"
    assert err.value.in_python().hint == "give a TOML file of the boxes put down: scene=FILE"
    # raised in a worker process, it reaches the parent whole (pickled by its parts)
    import pickle

    back = pickle.loads(pickle.dumps(err.value))
    assert type(back) is NeedsScene and (back.message, back.hint) == (err.value.message, err.value.hint)
    assert back.in_python().hint == err.value.in_python().hint
    plain = pickle.loads(pickle.dumps(BadInput("x.h5: not an artifact", hint="run cdrb collect")))
    assert (plain.message, plain.hint, str(plain)) == (
        "x.h5: not an artifact",
        "run cdrb collect",
        "x.h5: not an artifact (run cdrb collect)",
    )
    corner = _scene_file(tmp_path, "[[boxes]]\ncenter = [1.10, 1.05, 0.45]\nhalf = [0.02, 0.02, 0.02]\n", "corner")
    # none found: said as none (not "fewer than the 1 asked for" of an eval's first check), and fewer episodes
    # are not offered as the way out
    for n in (1, 3):
        with pytest.raises(BadInput, match=r"block the shortest route of none of \d+ drawn pairs \(") as err:
            fam.draw_protocol_episodes(fam.with_map(spec, corner), n, 0, 1, "detour")
        assert "fewer episodes" not in err.value.hint


@pytest.mark.parametrize(
    "text,needle",
    [
        ("[[boxes]\n", "not valid TOML"),
        ("[[boxes]]\ncenter = [1.3, 0.5, 0.5]\nhalf = [0.1, 0.1, 0.1]\ncolour = 'red'\n", "unknown key"),
        ("[[boxes]]\ncenter = [1.3, 0.5]\nhalf = [0.1, 0.1, 0.1]\n", "boxes[0].center: expected three numbers"),
        ("[[boxes]]\ncenter = [1.3, 0.5, true]\nhalf = [0.1, 0.1, 0.1]\n", "boxes[0].center: expected three numbers"),
        ("[[boxes]]\ncenter = [1.3, 0.5, 0.5]\nhalf = [0.1, -0.1, 0.1]\n", "boxes[0].half: each half size"),
        (
            "[[boxes]]\ncenter = [1.3, 0.5, 0.5]\nhalf = [0.1, 0.1, 0.1]\n[[boxes]]\ncenter = [1e9, 0, 0]\n"
            "half = [0.1, 0.1, 0.1]\n",
            "boxes[1].center beyond",
        ),
        ("name = 'x'\n", "boxes: Field required"),
        ("[[boxes]]\ncenter = [1.36, 0.76, 0.60]\nhalf = [0.01, 0.01, 0.01]\n", "overlaps the gripper at its home"),
        # a box over the whole goal region: nothing left to draw
        (
            "[[boxes]]\ncenter = [1.34, 0.45, 0.56]\nhalf = [0.2, 0.12, 0.16]\n"
            "[[boxes]]\ncenter = [1.34, 1.05, 0.56]\nhalf = [0.2, 0.12, 0.16]\n",
            "leave (almost) no room to draw",
        ),
        # a pocket of room that one draw in thousands finds: the first episode seed's draw succeeds, others fail
        (
            "[[boxes]]\ncenter = [1.34, 0.50, 0.47745]\nhalf = [0.25, 0.13, 0.17745]\n"
            "[[boxes]]\ncenter = [1.34, 1.00, 0.47745]\nhalf = [0.25, 0.13, 0.17745]\n",
            "(0% of candidate draws kept, fewer than 1%)",
        ),
        ("[[boxes]]\ncenter = [1" + "0" * 5000 + ", 0.5, 0.5]\nhalf = [0.1, 0.1, 0.1]\n", "integer of more than"),
        # a roof on the corridor's walls: clear of the gripper, but the arm's wrist reaches through it at the start
        ("[[boxes]]\ncenter = [1.30, 0.749, 0.78]\nhalf = [0.16, 0.125, 0.01]\n", "cuts through the robot's wrist"),
    ],
)
def test_bad_fetch_scene_files_get_one_line_errors(tmp_path, text, needle):
    spec = make_spec("fetch-reach-obstacle")
    with pytest.raises(BadInput, match=re.escape(needle)) as err:
        family_of(spec).with_map(spec, _scene_file(tmp_path, text))
    assert str(tmp_path) in err.value.message and "\n" not in err.value.message


def test_scene_files_of_the_other_family_are_refused():
    with pytest.raises(BadInput, match="a maze map, but fetch-reach-obstacle is a Fetch task"):
        family_of(make_spec("fetch-reach-obstacle")).with_map(make_spec("fetch-reach-obstacle"), NORTH)
    with pytest.raises(BadInput, match="a scene settings file, but maze-tight is a maze"):
        family_of(make_spec("maze-tight")).with_map(make_spec("maze-tight"), X_PLUS)


def test_an_eval_says_when_the_expert_itself_runs_out_of_time_on_its_pairs(tmp_path, cdrb):
    """A scene whose walls make every route far longer than the training map's timing: the scripted expert cannot
    reach the goals within the episode limit, so no method can, and the eval says so in one warning line; in the
    training map the same eval says nothing."""
    room = ["#########", "#S.....G#", *["#.......#"] * 4, "#########"]
    serpentine = ["#########", "#S#...#G#", *["#.#.#.#.#"] * 3, "#...#...#", "#########"]
    (tmp_path / "room.txt").write_text("\n".join(room) + "\n")
    (tmp_path / "serpentine.txt").write_text("\n".join(serpentine) + "\n")
    demos, model = tmp_path / "d.h5", tmp_path / "m.h5"
    assert cdrb("collect", "--maze-map", tmp_path / "room.txt", "-n", "4", "--out", demos).returncode == 0
    assert cdrb("train", demos, "--method", "straight", "--out", model).returncode == 0
    runs = {
        "room": cdrb("eval", model, "--episodes", "3", "--seeds", "0", "--out", tmp_path / "e1.h5"),
        "scene": cdrb(
            "eval",
            model,
            "--scene",
            tmp_path / "serpentine.txt",
            "--protocol",
            "detour",
            "--episodes",
            "3",
            "--seeds",
            "0",
            "--out",
            tmp_path / "e2.h5",
        ),  # fmt: skip
    }
    assert all(r.returncode == 0 for r in runs.values()), [r.stderr[-500:] for r in runs.values()]
    assert "expert reaches the goal in only" not in runs["room"].stderr
    said = [ln for ln in runs["scene"].stderr.splitlines() if "expert reaches the goal in only" in ln]
    assert len(said) == 1 and "0 of 3 episodes" in said[0] and "extra_steps" in said[0], runs["scene"].stderr


def test_a_scene_over_the_whole_buffer_is_one_line_that_says_what_to_do(tiny_models, monkeypatch):
    """Masking removes every buffer state a new obstacle covers; when that is all of them the sampler has nothing
    to draw from, which is said in one line with the way out (planning without the mask)."""
    from cdrb_cli.stages.avoid import prepare_planner
    from cdrb_cli.stages.plan import load_planner

    model = tiny_models["cdrb"]
    spec = family_of(model.manifest.env).with_map(model.manifest.env, NORTH)
    family = family_of(spec)
    monkeypatch.setattr(type(family), "in_collision", lambda self, spec, states: np.ones(states.shape[:-1], bool))
    with pytest.raises(BadInput) as err:
        prepare_planner(load_planner(model), spec, AvoidConfig(mask_buffer=True))
    assert "cover every state" in err.value.message and "avoid.mask_buffer=false" in err.value.hint


def test_a_route_buffer_of_another_task_names_the_setting(small_data):
    """The route buffer is the setting avoid.route_buffer (--set, a settings file, or the older flag): the error
    names the setting, whichever way it was given."""
    from cdrb_cli.stages.avoid import buffer_states

    _, buffer = small_data
    with pytest.raises(BadInput) as err:
        buffer_states(buffer, buffer.manifest.env, "maze")
    assert err.value.message.startswith(f"avoid.route_buffer = {buffer.path}: a buffer of maze-tight")


def test_a_plan_between_two_unconnected_regions_is_said_to_be_impossible(tmp_path):
    """Start and goal in two free regions no route joins: the warning says so (no data or avoidance can help),
    instead of advice about where the data starts; points in one region, on a wall or off the map are not judged
    unconnected."""
    from cdrb_cli.stages.plan_warnings import disconnected_warning

    (tmp_path / "two.txt").write_text("#######\n#S.G#S#\n#...#G#\n#######\n")
    family = family_of(make_spec("maze"))
    spec = family.spec_from_file(tmp_path / "two.txt")
    g = MazeGeometry(spec.scene.maze)
    left, left2, right, wall = (g.cell_to_xy(c) for c in ([1, 1], [2, 3], [1, 5], [1, 4]))
    starts = np.array([left, left, wall, [50.0, 50.0]])
    goals = np.array([right, left2, right, right])
    np.testing.assert_array_equal(family.unconnected(spec, starts, goals), [True, False, False, False])
    plan = np.stack([np.linspace(left, right, 8), np.linspace(left, left2, 8)])  # the first jumps the wall
    plans = np.concatenate([plan, np.zeros((2, 8, 2))], axis=-1)
    said = disconnected_warning(spec, plans, stride=1)
    assert "1 of 2 plans join a start and a goal that no free route connects" in said and "--starts" not in said
