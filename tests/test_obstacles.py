"""New obstacles at plan and eval time, no retraining: the map check, the detour protocol, the masked buffer, best-of-N,
buffer routes and collision guidance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.configs import AvoidConfig
from cdrb_cli.envs.pointmaze.maze import MazeGeometry
from cdrb_cli.envs.registry import family_of, make_spec
from cdrb_cli.errors import BadInput

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
    from cdrb_cli.stages.plan import Avoidance

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


# ------------------------------------------------------------------------------------------------ masking
def test_masked_buffer_never_restores_a_state_inside_the_new_wall(tiny_models):
    from cdrb_cli.stages.plan import load_planner, prepare_planner, sample_plans

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


def test_mask_and_route_refused_where_they_do_not_apply(tiny_models, cdrb, tmp_path):
    out = tmp_path / "e.h5"
    r = cdrb("eval", tiny_models["diffuser"].path, "--mask-buffer", "-n", "2", "--seeds", "0", "--out", out)
    assert r.returncode == 2 and "--mask-buffer: diffuser samples from no replay buffer" in r.stderr
    r = cdrb("eval", tiny_models["cdrb"].path, "--guide-scale", "0.1", "-n", "2", "--seeds", "0", "--out", out)
    assert r.returncode == 2 and "--guide-scale: cdrb has no guided sampling" in r.stderr
    r = cdrb("eval", tiny_models["mlp"].path, "--route-k", "2", "-n", "2", "--seeds", "0", "--out", out)
    assert r.returncode == 2 and "--route-k: mlp cannot restore" in r.stderr
    r = cdrb("eval", tiny_models["diffuser"].path, "--route-k", "2", "-n", "2", "--seeds", "0", "--out", out)
    assert r.returncode == 2 and "add --route-buffer" in r.stderr
    r = cdrb("eval", tiny_models["cdrb"].path, "--protocol", "detour", "-n", "2", "--seeds", "0", "--out", out)
    assert r.returncode == 2 and "add --maze-map" in r.stderr
    assert not out.exists() and len(r.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------------ routes
def test_buffer_route_takes_free_steps_around_the_new_wall():
    from cdrb_cli.stages.routes import BufferGraph

    base = make_spec("maze-tight")
    spec = family_of(base).with_map(base, NORTH)
    family = family_of(spec)
    g = MazeGeometry(spec.scene.maze)
    free = np.argwhere(g.free)
    rng = np.random.default_rng(0)
    xy = np.concatenate([g.cell_to_xy(free) + rng.uniform(-0.3, 0.3, (len(free), 2)) for _ in range(3)])
    states = np.concatenate([xy, np.zeros((len(xy), 2))], 1)
    states = states[~family.in_collision(spec, states)]
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

    planner = api.Planner(tiny_models["cdrb"].path, maze_map=NORTH, mask_buffer=True, best_of=2, route_k=2)
    assert planner.spec.id == "maze-tight+maze-tight-closed-north"
    g = MazeGeometry(planner.spec.scene.maze)
    plans = planner.plan(start=g.cell_to_xy([5, 7]), goal=g.cell_to_xy([1, 1]), n=3, seed=0)
    assert plans.states.shape[0] == 3
    assert not family_of(planner.spec).in_collision(planner.spec, plans.states[:, 1:-1]).any()
    with pytest.raises(BadInput, match="inside a wall"):  # the closed gap is a wall now
        planner.plan(start=g.cell_to_xy([4, 7]), goal=g.cell_to_xy([1, 1]))


def test_pairs_without_a_buffer_route_are_said(tiny_models, capsys):
    """A start the buffer cannot reach by a free step gets the straight line, and the count is reported."""
    from cdrb_cli.stages.plan import load_planner, prepare_planner, sample_plans, warn_unrouted

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
