"""The OGBench family: OGBench's PointMaze mazes, tasks, agent, noisy expert and data episodes, checked against the
definitions its package and data-generation script use (docs/environments.md states them)."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli.envs.family import Episode
from cdrb_cli.envs.ogbench import COLLECT_STEPS, STITCH_CELLS, OGBenchFamily, ogbench_spec
from cdrb_cli.envs.ogbench.env import PointMazeOG
from cdrb_cli.envs.ogbench.expert import OGBenchExpert, OGBenchExpertConfig
from cdrb_cli.envs.ogbench.maze import MAPS, TASKS, OGBenchGeometry, layout
from cdrb_cli.seeding import STREAM_COLLECT, STREAM_EVAL

FAMILY = OGBenchFamily()


@pytest.mark.parametrize(("maze", "free", "vertex"), [("medium", 26, 21), ("large", 46, 22), ("giant", 86, 46)])
def test_the_mazes_have_ogbench_cells_and_coordinates(maze, free, vertex):
    g = OGBenchGeometry(layout(maze))
    assert (int(g.free.sum()), len(g.vertex_cells)) == (free, vertex)
    # cell (i, j) at (4j - 4, 4i - 4): row i grows along y
    np.testing.assert_allclose(g.cell_to_xy([[1, 1], [2, 5]]), [[0, 0], [16, 4]])
    rng = np.random.default_rng(0)
    cells = np.argwhere(g.free)
    xy = g.cell_to_xy(cells) + rng.uniform(-1.99, 1.99, cells.shape)
    np.testing.assert_array_equal(g.xy_to_cell(xy), cells)
    # every task joins two free cells one path apart, and the border is wall
    for start, goal in TASKS[maze]:
        assert g.free[start] and g.free[goal] and g.bfs(goal)[start] > 0
    assert not g.free[0].any() and not g.free[-1].any() and not g.free[:, 0].any() and not g.free[:, -1].any()


def test_a_step_moves_by_a_fifth_of_the_action_and_walls_push_back():
    spec = ogbench_spec("medium", "navigate")
    env = PointMazeOG(spec)
    env.place([4.0, 4.0])
    np.testing.assert_allclose(env.step([1.0, 0.5]), [4.2, 4.1], atol=1e-9)
    np.testing.assert_allclose(env.step([3.0, -7.0]), [4.4, 3.9], atol=1e-9)  # clipped to [-1, 1]
    # cell (1, 1) at (0, 0) has a wall cell to its left (x <= -2): pushed into it, the 0.7 m sphere stops at the face
    env.place([0.0, 0.0])
    xs = [env.step([-1.0, 0.0])[0] for _ in range(40)]
    assert -2 + 0.7 - 0.05 < min(xs) < -2 + 0.7 and abs(xs[-1] - xs[-2]) < 1e-3
    # the collision test counts a state only deeper than the contacts let the agent go
    assert not FAMILY.in_collision(spec, np.array([[min(xs), 0.0]]))[0]
    assert FAMILY.in_collision(spec, np.array([[-1.4, 0.0]]))[0]  # 0.6 m from the face


def test_evaluation_runs_the_five_tasks_in_turn_with_ogbench_noise():
    spec = ogbench_spec("large", "stitch")
    episodes = FAMILY.draw_episodes(spec, 10, seed=3, stream=STREAM_EVAL)
    assert [(e.start, e.goal) for e in episodes] == [TASKS["large"][i % 5] for i in range(10)]
    g, env = OGBenchGeometry(spec.scene.maze), PointMazeOG(spec)
    starts, goals = FAMILY.reset_states(spec, episodes, env)
    for e, s, goal in zip(episodes, starts, goals):
        assert np.abs(s - g.cell_to_xy(e.start)).max() <= 1.0 and np.abs(goal - g.cell_to_xy(e.goal)).max() <= 1.0
    again, _ = FAMILY.reset_states(spec, episodes[:2], env)
    np.testing.assert_array_equal(again, starts[:2])
    assert len({tuple(s.round(6)) for s in starts}) == 10  # each episode its own noise


def test_collect_draws_ogbench_data_episodes():
    nav, stitch = ogbench_spec("giant", "navigate"), ogbench_spec("giant", "stitch")
    g = OGBenchGeometry(nav.scene.maze)
    vertex = {tuple(c) for c in g.vertex_cells.tolist()}
    for e in FAMILY.draw_episodes(nav, 50, 0, STREAM_COLLECT):
        assert g.free[e.start] and e.goal in vertex
    for e in FAMILY.draw_episodes(stitch, 50, 0, STREAM_COLLECT):
        assert g.bfs(e.start)[e.goal] == STITCH_CELLS
    assert FAMILY.collect_limit(nav) == 2000 == COLLECT_STEPS[("navigate", "giant")]
    assert FAMILY.collect_limit(ogbench_spec("medium", "navigate")) == 1000
    assert FAMILY.collect_limit(stitch) == 200


@pytest.mark.parametrize("maze", sorted(MAPS))
def test_the_noiseless_oracle_reaches_every_task_goal_cell(maze):
    """Without noise the expert walks the grid path to the goal cell and stops at its centre: OGBench's oracle aims
    at cell centres, so the noisy goal itself is reached only where the noise put it within 1 m of the centre."""
    spec = ogbench_spec(maze, "stitch")
    env, g = PointMazeOG(spec), OGBenchGeometry(spec.scene.maze)
    expert = OGBenchExpert(spec, OGBenchExpertConfig(noise=0.0))
    for k, (start, goal) in enumerate(TASKS[maze]):
        state, target = env.reset(Episode(k, start, goal))
        expert.reset(state, target, np.random.default_rng(k))
        cells = 25 * g.bfs(goal)[start]  # 4 m cells at 0.2 m per step, with room for the corners
        for _ in range(cells):
            state = env.step(expert.act(state))
        centre = g.cell_to_xy(goal)
        assert np.linalg.norm(state - centre) < 0.25, (maze, k)
        if np.linalg.norm(target - centre) <= 0.75:  # a goal the centre is within 1 m of
            assert FAMILY.success(spec, state, target), (maze, k)


def test_navigate_data_redraws_goals_and_stays_out_of_walls(cdrb, tmp_path):
    from cdrb_cli import artifacts

    out = tmp_path / "demos.h5"
    r = cdrb("collect", "pointmaze-medium-navigate-v0", "--episodes", "3", "--seed", "1", "--out", out)
    assert r.returncode == 0, r.stderr
    demos = artifacts.load(out, "demos")
    assert list(np.asarray(demos.arrays["episodes/length"])) == [1001] * 3
    states = np.asarray(demos.arrays["steps/observations"])
    spec = demos.manifest.env
    assert not FAMILY.in_collision(spec, states).any()
    # the noisy expert, as OGBench's: unit direction plus N(0, 0.5^2), clipped; so many actions sit on the bounds
    actions = np.asarray(demos.arrays["steps/actions"])
    assert 0.2 < np.mean(np.abs(actions) == 1.0) < 0.8
    # goals re-drawn on success: one episode of 1,000 steps visits several vertex cells' surroundings
    g = OGBenchGeometry(spec.scene.maze)
    visited = {tuple(c) for c in g.xy_to_cell(states[:1001]).tolist()}
    assert len(visited) > 12


def _official_file(path, lengths=(7, 5), obs_dim=2, pickled=False):
    """A small file in OGBench's format: observations, actions and qpos/qvel as float32, terminals true on each
    episode's last row (as its generation script writes them)."""
    rng = np.random.default_rng(0)
    n = sum(lengths)
    obs = np.cumsum(rng.uniform(-0.2, 0.2, (n, obs_dim)), axis=0).astype(np.float32)
    terminals = np.zeros(n, dtype=bool)
    terminals[np.cumsum(lengths) - 1] = True
    arrays = dict(observations=obs, actions=rng.uniform(-1, 1, (n, 2)).astype(np.float32), terminals=terminals)
    arrays |= dict(qpos=obs.copy(), qvel=np.zeros((n, 2), np.float32))
    if pickled:
        arrays["observations"] = np.array([obs, None], dtype=object)
    np.savez_compressed(path, **arrays)
    return arrays


def test_an_import_never_writes_over_a_file_without_force_nor_over_its_input(cdrb, tmp_path):
    src = tmp_path / "pointmaze-medium-navigate-v0-val.npz"
    _official_file(src)
    before = src.read_bytes()
    r = cdrb("import", "npz", src, "--out", src, "--force")
    assert r.returncode == 2 and "is an input of this command" in r.stderr and src.read_bytes() == before, r.stderr
    mine = tmp_path / "notes.txt"
    mine.write_text("my notes\n")
    r = cdrb("import", "npz", src, "--out", mine)
    assert r.returncode == 2 and "file exists" in r.stderr and mine.read_text() == "my notes\n", r.stderr
    assert cdrb("import", "npz", src, "--out", mine, "--force").returncode == 0


def test_an_unknown_env_is_named_with_the_imports_flag(cdrb, tmp_path):
    src = tmp_path / "pointmaze-medium-navigate-v0-val.npz"
    _official_file(src)
    r = cdrb("import", "npz", src, "--env", "nope", "--out", tmp_path / "d.h5")
    assert r.returncode == 2 and "--env 'nope': not an environment" in r.stderr and "--maze-map" not in r.stderr
    assert not (tmp_path / "d.h5").exists()


def test_an_official_file_imports_episode_by_episode(cdrb, tmp_path):
    from cdrb_cli import artifacts

    src = tmp_path / "pointmaze-medium-navigate-v0-val.npz"
    raw = _official_file(src)
    r = cdrb("import", "npz", src, "--out", tmp_path / "d.h5", "--valid-fraction", "0")
    assert r.returncode == 0, r.stderr
    demos = artifacts.load(tmp_path / "d.h5", "demos")
    assert demos.manifest.env.id == "pointmaze-medium-navigate-v0"  # from the file's name
    assert list(demos.arrays["episodes/length"]) == [7, 5]
    np.testing.assert_allclose(demos.arrays["steps/observations"], raw["observations"])
    actions = np.asarray(demos.arrays["steps/actions"])
    # the last action of each episode has no next observation: dropped, as OGBench's loader drops it
    np.testing.assert_allclose(actions[:6], raw["actions"][:6])
    np.testing.assert_allclose(actions[7:11], raw["actions"][7:11])  # the second episode, rows 7..11
    np.testing.assert_array_equal(actions[[6, 11]], 0.0)
    goals = np.asarray(demos.arrays["steps/desired_goals"])
    np.testing.assert_allclose(goals[:7], np.repeat(raw["observations"][6:7], 7, axis=0))
    assert demos.manifest.config.expert.kind == "ogbench-dataset"
    assert len(demos.manifest.config.expert.sha256) == 64


@pytest.mark.parametrize(
    ("make", "name", "message"),
    [
        (lambda p: _official_file(p, pickled=True), "pointmaze-large-stitch-v0.npz", "object arrays, which are never"),
        (lambda p: _official_file(p, obs_dim=3), "pointmaze-large-stitch-v0.npz", "observations (12, 3)"),
        (lambda p: np.savez(p, observations=np.zeros((3, 2))), "pointmaze-large-stitch-v0.npz", "no actions"),
        (lambda p: _official_file(p), "maze-data.npz", "its name says no environment"),
        (lambda p: p.write_bytes(b"PK\x03\x04 not a zip"), "pointmaze-giant-navigate-v0.npz", "not a readable"),
        (
            lambda p: np.save(p.with_suffix(".npy"), np.zeros(3)) or p.with_suffix(".npy").rename(p),
            "pointmaze-giant-navigate-v0.npz",
            "not a readable .npz file (ValueError: one array, not an archive of named arrays)",
        ),
        (
            lambda p: np.savez(
                p, observations=np.array([["a", "b"]] * 4), actions=np.zeros((4, 2)), terminals=np.eye(4)[3]
            ),
            "pointmaze-medium-stitch-v0.npz",
            "observations is a 2-d <U1",
        ),
        (
            lambda p: np.savez(
                p, observations=np.full((4, 2), 1e300), actions=np.zeros((4, 2)), terminals=np.eye(4)[3]
            ),
            "pointmaze-medium-stitch-v0.npz",
            "values beyond 1e6",
        ),
        (
            lambda p: np.savez(p, observations=np.float64(3.0), actions=np.zeros((4, 2)), terminals=np.eye(4)[3]),
            "pointmaze-medium-stitch-v0.npz",
            "observations is a 0-d float64",
        ),
        (
            lambda p: np.savez(p, observations=np.zeros((0, 2)), actions=np.zeros((0, 2)), terminals=np.zeros(0)),
            "pointmaze-medium-stitch-v0.npz",
            "0 rows, fewer than the two of one step (the file is empty or damaged)",
        ),
        # finite, under the reader's bound, but a maze away from any map of the family: refused before writing
        (
            lambda p: np.savez(
                p, observations=np.full((4, 2), 1000.0), actions=np.zeros((4, 2)), terminals=np.eye(4)[3]
            ),
            "pointmaze-medium-stitch-v0.npz",
            "far outside the environment's",
        ),
    ],
)
def test_a_bad_official_file_is_refused_in_one_line(cdrb, tmp_path, make, name, message):
    src = tmp_path / name
    make(src)
    r = cdrb("import", "npz", src, "--out", tmp_path / "d.h5")
    assert r.returncode != 0 and message in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "d.h5").exists()


def test_ogbench_ids_keep_their_version_as_gymnasium_ids():
    import gymnasium

    from cdrb_cli.gym import gym_id, register_envs

    assert gym_id("pointmaze-medium-navigate-v0") == "cdrb/pointmaze-medium-navigate-v0"
    assert gym_id("maze") == "cdrb/maze-v0"
    assert "cdrb/pointmaze-giant-stitch-v0" in register_envs()
    env = gymnasium.make("cdrb/pointmaze-large-navigate-v0")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (2,)
    env.close()
