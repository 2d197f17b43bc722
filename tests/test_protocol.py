"""The comparison protocol: tuning vs test pairs, the official-code protocol and executor, the plan
clock's timeout, and the plan metrics that catch jumps through walls."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli.envs.geometry import (
    box_arrays,
    largest_jump,
    path_crosses_boxes,
    segment_box_distance,
    segment_hits_boxes,
)
from cdrb_cli.envs.pointmaze import OFFICIAL_SUCCESS_RADIUS
from cdrb_cli.envs.pointmaze.env import PointMaze
from cdrb_cli.envs.pointmaze.expert import MazeExpert
from cdrb_cli.envs.pointmaze.maze import MazeGeometry
from cdrb_cli.envs.registry import CONTROLLERS, family_of, make_spec
from cdrb_cli.seeding import EVAL_STREAMS
from cdrb_cli.stages.collect import rollout
from cdrb_cli.stages.evaluate import run_episode


def test_segments_through_a_wall_are_caught_though_both_ends_are_free():
    spec = make_spec("maze-tight")
    fam = family_of(spec)
    # either side of the ring's west wall (x = -3 m column of wall cells), at rest, both in free space
    a, b = np.array([-4.0, 2.0, 0, 0]), np.array([-2.0, 2.0, 0, 0])
    assert not fam.in_collision(spec, np.stack([a, b])).any()
    assert fam.path_in_collision(spec, np.stack([a, b])[None])[0]
    # the same length inside one free region does not cross
    c, d = np.array([-5.0, 5.0, 0, 0]), np.array([-3.0, 5.0, 0, 0])
    assert not fam.path_in_collision(spec, np.stack([c, d])[None])[0]
    # a path that stays free state by state but teleports through the wall in its last step
    path = np.concatenate([np.linspace(a, a + [0, 0.5, 0, 0], 10), b[None]])
    assert fam.path_in_collision(spec, path[None])[0] and not fam.in_collision(spec, path).any()


def test_segment_distance_matches_dense_sampling():
    """The ternary search finds the segment's minimum distance to the boxes (checked against 2,001 points)."""
    spec = make_spec("maze")
    centers, halves = box_arrays(spec.obstacles)
    rng = np.random.default_rng(0)
    a = rng.uniform(-7, 7, size=(300, 2))
    b = a + rng.normal(scale=2.0, size=(300, 2))
    exact = segment_box_distance(a, b, centers, halves)
    t = np.linspace(0, 1, 2001)[:, None, None]
    pts = a[None] + t * (b - a)[None]  # (2001, 300, 2)
    gap = np.abs(pts[..., None, :] - centers) - halves
    dense = np.sqrt(np.square(np.maximum(gap, 0)).sum(-1)).min(-1).min(0)
    assert np.all(exact <= dense + 1e-9)  # never above a sampled point
    np.testing.assert_allclose(exact, dense, atol=np.linalg.norm(b - a, axis=1).max() / 2000 + 1e-9)
    for r in (0.1, 0.5):  # the pruned search decides "closer than r" exactly like the full one
        pruned = segment_box_distance(a, b, centers, halves, within=r)
        np.testing.assert_array_equal(pruned < r, exact < r)
        np.testing.assert_allclose(pruned[exact < r], exact[exact < r])
    ob = spec.obstacles
    crossing = path_crosses_boxes(np.stack([a, b], axis=1), ob.model_copy(update={"dims": [0, 1]}))
    assert crossing.any() and not crossing.all()


def test_the_slab_test_says_whether_a_segment_meets_a_box_as_the_distance_does():
    """The Fetch experts ask "does this leg meet a wall?" of the slab test: it must answer as the segment's distance
    does, for oblique, axis-parallel and zero-length segments, and for one that runs along a face."""
    rng = np.random.default_rng(1)
    for trial in range(3000):
        n = int(rng.integers(1, 4))
        centers, halves = rng.uniform(-1, 1, (n, 3)), rng.uniform(0.05, 0.4, (n, 3))
        a = rng.uniform(-1.5, 1.5, 3)
        b = a + rng.normal(0, 0.6, 3)
        if trial % 5 == 0:
            b = a.copy()
        elif trial % 5 == 1:
            b = a.copy()
            b[trial % 3] += rng.normal(0, 1)
        elif trial % 5 == 2:  # along the face x = high of the first box, inside its y-z extent
            a = centers[0] + halves[0] * np.array([1.0, 0.3, -0.2])
            b = a + np.array([0.0, 0.2, 0.1])
        want = segment_box_distance(a[None], b[None], centers, halves)[0] < 1e-9
        assert segment_hits_boxes(a, b, centers, halves, 1e-9) == want, (a, b, centers, halves)
    assert not segment_hits_boxes(np.zeros(3), np.ones(3), np.zeros((0, 3)), np.zeros((0, 3)), 1e-9)


def test_largest_jump_against_the_dynamics():
    spec = make_spec("maze")
    fam = family_of(spec)
    limit = fam.max_step(spec) * spec.plan_stride
    d = PointMaze(spec).dynamics
    v = 5.0 + d["dt"] * (d["gear"] - d["damping"] * 5.0) / (d["mass"] + d["dt"] * d["damping"])
    assert np.isclose(limit, np.sqrt(2) * v * d["dt"] * 2)
    env = PointMaze(spec)
    ep = fam.draw_episodes(spec, 1, 0, EVAL_STREAMS["test"])[0]
    S, *_ = rollout(env, MazeExpert(spec), spec, ep, spec.episode_limit)
    plan = S[:: spec.plan_stride]
    assert largest_jump(plan, [0, 1]) <= limit  # what the ball did is always within the bound
    assert largest_jump(S, [0, 1]) <= fam.max_step(spec)  # per env step too, at the expert's top speed
    plan[-1, :2] += 3.0
    assert largest_jump(plan, [0, 1]) > limit


def test_tuning_and_test_pairs_are_different_streams():
    spec = make_spec("maze-tight")
    fam = family_of(spec)
    test = fam.draw_episodes(spec, 50, 0, EVAL_STREAMS["test"])
    tune = fam.draw_episodes(spec, 50, 0, EVAL_STREAMS["tune"])
    assert not {e.seed for e in test} & {e.seed for e in tune}
    s_test, _ = fam.reset_states(spec, test)
    s_tune, _ = fam.reset_states(spec, tune)
    d = np.linalg.norm(s_test[:, None, :2] - s_tune[None, :, :2], axis=-1)
    assert d.min() > 1e-6  # no tuning start is a test start


def test_official_protocol_goals_at_cell_centres_same_starts():
    spec = make_spec("maze")
    fam = family_of(spec)
    official = fam.protocol_spec(spec, "official-code")
    assert official.success_radius == OFFICIAL_SUCCESS_RADIUS and not official.scene.goal_noise
    assert fam.protocol_controller("official-code") == "waypoint" and fam.protocol_controller(fam.protocol) is None
    eps = fam.draw_episodes(spec, 10, 1, EVAL_STREAMS["tune"])
    s0, g0 = fam.reset_states(spec, eps)
    s1, g1 = fam.reset_states(official, eps)
    np.testing.assert_array_equal(s0, s1)
    centres = MazeGeometry(spec.scene.maze).cell_to_xy(np.array([e.goal for e in eps]))
    np.testing.assert_allclose(g1, centres)
    assert np.abs(g0 - centres).max() > 0.01  # the default protocol's goals carry the stock noise


def test_plan_clock_timeout():
    spec = make_spec("maze")
    env = PointMaze(spec)
    entry = CONTROLLERS.get("pd")
    plan = np.zeros((10, 4))
    plan[:, 0] = np.arange(10.0)
    stuck = entry.build(spec, env, entry.config(max_lag=0.6), 2)
    waits = entry.build(spec, env, entry.config(max_lag=0.6, max_wait=3), 2)
    for c in (stuck, waits):
        c.reset(plan)
    at_start = np.zeros(4)
    assert [stuck.plan_time(at_start, t) for t in range(8)] == [0] * 8
    # paused 3 steps on planned state 1 (plan time 0..1 at stride 2), then on to state 2 (plan time 2), and so on
    assert [waits.plan_time(at_start, t) for t in range(8)] == [0, 0, 0, 2, 2, 2, 2, 4]


def test_look_ahead_moves_the_clock_to_a_ball_past_its_target():
    """A plan whose first states lie behind a ball moving along it (a re-plan from a moving state): without
    ``look_ahead`` the gated clock holds the ball to planned state 1, which it has passed; with it the clock jumps
    to the state after the nearest of the next ``look_ahead``, and never further."""
    spec = make_spec("maze")
    env = PointMaze(spec)
    entry = CONTROLLERS.get("pd")
    plan = np.zeros((20, 4))
    plan[:, 0] = 0.1 * np.arange(20.0)
    plan[:, 2] = 5.0  # moving along +x
    plan[1, 0] = -0.5  # the first planned step jumps back
    plain = entry.build(spec, env, entry.config(max_lag=0.6), 2)
    ahead = entry.build(spec, env, entry.config(max_lag=0.6, look_ahead=4), 2)
    for c in (plain, ahead):
        c.reset(plan)
    ball = np.array([0.3, 0.0, 5.0, 0.0])  # nearest planned states: 3 (0.3 m), within the 4 after state 1
    assert plain.plan_time(ball, 0) // 2 + 1 == 1  # still driven back to state 1 (0.8 m away: the clock pauses)
    assert plain.act(ball, 1)[0] < 0  # pushed backwards
    assert ahead.plan_time(ball, 0) // 2 + 1 == 4  # jumped to state 3, driven to state 4, and the clock runs on
    assert ahead.act(ball, 1)[0] > 0
    far = entry.build(spec, env, entry.config(max_lag=0.6, look_ahead=1), 2)
    far.reset(plan)
    assert far.plan_time(np.array([1.5, 0.0, 0.0, 0.0]), 0) // 2 + 1 <= 3  # at most look_ahead states on, per step


def test_official_executor_reaches_goals_of_expert_plans():
    """The waypoint executor (kp 1, kd 0.1, <= 5 steps per state) replaying expert plans under the official
    protocol: it follows the plan and ends within the official 0.55 m."""
    base = make_spec("maze")
    fam = family_of(base)
    spec = fam.protocol_spec(base, "official-code")
    env = PointMaze(spec)
    entry = CONTROLLERS.get("waypoint")
    ctrl = entry.build(spec, env, entry.config(), spec.plan_stride)
    ok = 0
    eps = fam.draw_episodes(spec, 8, 2, EVAL_STREAMS["tune"])
    for ep in eps:
        S, _, goal, _ = rollout(env, MazeExpert(spec), spec, ep, base.episode_limit)
        ctrl.reset(S[:: spec.plan_stride])
        res = run_episode(env, spec, ep, ctrl.act, spec.episode_limit)
        ok += res.success and not res.collision
    assert ok >= 7, ok


@pytest.mark.parametrize(
    "name, settings",
    [
        ("pd", {"max_wait": 0}),
        ("pd", {"max_lag": None, "max_wait": 5}),
        ("pd", {"max_lag": None, "look_ahead": 4}),
        ("inverse-dynamics", {"look_ahead": -1}),
        ("waypoint", {"reach": 0.0}),
        ("waypoint", {"max_steps": 0}),
    ],
)
def test_controller_settings_are_bounded(name, settings):
    with pytest.raises(ValueError):
        CONTROLLERS.get(name).config(**settings)


def test_a_point_agent_inside_a_box_collides():
    """With no agent radius (inflate 0), a state or a segment inside a box still counts."""
    spec = make_spec("maze")
    ob = spec.obstacles.model_copy(update={"inflate": 0.0})
    from cdrb_cli.envs.geometry import in_boxes

    inside = np.array([[ob.centers[0][0], ob.centers[0][1], 0, 0]])
    assert in_boxes(inside, ob).all()
    across = np.stack([inside[0] - [2, 0, 0, 0], inside[0] + [2, 0, 0, 0]])[None]
    assert path_crosses_boxes(across, ob).all()


def test_a_point_agent_cannot_pass_where_two_boxes_touch():
    """A point agent's segment is as closed as its states: passing through the corner two boxes share (a gap of no
    width), or grazing a corner, crosses, as a state there collides; missing the corner by a hair does not. The
    vectorised slab test answers each segment as the one-segment test does."""
    from cdrb_cli.envs.geometry import BoxObstacles, in_boxes, segments_hit_boxes

    ob = BoxObstacles(dims=[0, 1], centers=[[0.5, 0.5], [-0.5, -0.5]], half_sizes=[[0.5, 0.5]] * 2,
                      low=[-5, -5], high=[5, 5])  # fmt: skip
    through = np.array([[[-1.0, 1.0], [1.0, -1.0]]])
    assert in_boxes(np.zeros((1, 2)), ob).all() and path_crosses_boxes(through, ob).all()
    graze = np.array([[[-1.0, 0.0], [1.0, 2.0]]])  # touches the first box at its corner (0, 1) only
    assert path_crosses_boxes(graze, ob).all()
    assert not path_crosses_boxes(graze + [0.0, 1e-6], ob).any()
    rng = np.random.default_rng(0)
    a, b = rng.uniform(-2, 2, (200, 2)), rng.uniform(-2, 2, (200, 2))
    c, h = np.asarray(ob.centers), np.asarray(ob.half_sizes)
    want = [segment_hits_boxes(x, y, c, h, 0.0) for x, y in zip(a, b)]
    assert segments_hit_boxes(a, b, c, h).tolist() == want and 0 < sum(want) < 200


def test_a_state_that_is_not_a_point_collides():
    """A NaN or infinite state (a diverged sampler's) is in collision, and its plan crosses: a NaN compares false
    with every bound and every distance, and passed as free."""
    from cdrb_cli.envs.geometry import in_boxes

    spec = make_spec("maze-tight")
    fam, ob = family_of(spec), spec.obstacles
    g = MazeGeometry(spec.scene.maze)
    start = np.array([*g.cell_to_xy(g.start_cells[0]), 0.0, 0.0])
    for bad in (np.nan, np.inf):
        mid = start.copy()
        mid[0] = bad
        path = np.stack([start, mid, start])[None]
        assert in_boxes(mid[None], ob).all() and not in_boxes(start[None], ob).any()
        assert path_crosses_boxes(path, ob).all() and fam.path_in_collision(spec, path).all()
