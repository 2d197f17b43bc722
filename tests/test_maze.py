"""Maze maps, geometry and the collision check."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli.envs.geometry import box_distance, in_boxes
from cdrb_cli.envs.pointmaze import BALL_RADIUS
from cdrb_cli.envs.pointmaze.maze import MazeGeometry, parse_map
from cdrb_cli.envs.registry import family_of, list_envs, make_spec
from cdrb_cli.errors import BadInput

GOOD = """
// a small test map
#####
#S.G#
#####
"""


def test_parse_good_map():
    layout = parse_map(GOOD, "t")
    g = MazeGeometry(layout)
    assert (g.n_rows, g.n_cols) == (3, 5)
    assert g.start_cells.tolist() == [[1, 1]] and g.goal_cells.tolist() == [[1, 3]]


@pytest.mark.parametrize(
    "text, needle",
    [
        ("#####\n#S.G#\n####\n", "ragged"),
        ("#####\n#S.X#\n#####\n", "unknown map character 'X'"),
        ("#####\n#..G#\n#####\n", "no start cell"),
        ("#####\n#S..#\n#####\n", "no goal cell"),
        ("", "empty"),
        ("#####\n#S#G#\n#####\n", "no start cell can reach a goal cell other than itself"),
        ("##\n#S\n", "at least 3x3"),
        ("###\n#C#\n###\n", "no start cell can reach a goal cell other"),  # one cell, both start and goal
    ],
)
def test_parse_bad_maps(text, needle):
    with pytest.raises(BadInput) as info:
        parse_map(text, "bad", source="bad.txt")
    assert needle in str(info.value) and "bad.txt" in str(info.value)
    assert "\n" not in str(info.value)


def test_a_row_written_after_a_hash_and_space_is_named_when_the_map_lacks_its_cells():
    """``# `` starts a comment, so ``# S..#`` (a wall row with a space after its first ``#``) is not a row: the error
    about the missing start cell names that line; comments in prose, and maps that lack nothing, say nothing."""
    with pytest.raises(BadInput) as info:
        parse_map("#####\n# S..#\n#...#\n#..G#\n#####\n", "bad", source="bad.txt")
    assert "no start cell" in str(info.value) and "line 2 is read as a comment" in info.value.hint
    with pytest.raises(BadInput) as info:
        parse_map("# start cell S, goal cell G\n#####\n#S..#\n#####\n", "bad", source="bad.txt")
    assert "no goal cell" in str(info.value) and "comment" not in info.value.hint
    assert parse_map("# S.G\n#####\n#S.G#\n#####\n", "ok").rows == ["#####", "#S.G#", "#####"]


def test_bad_map_error_names_line(tmp_path):
    with pytest.raises(BadInput, match=r"bad.txt:3:4: unknown map character"):
        parse_map("#####\n#S.G#\n#..?#\n#####\n", "bad", source="bad.txt")


def test_start_or_goal_marked_on_a_wall_is_impossible_by_construction():
    # a start/goal cell *is* a free cell in this format; a wall cannot also be a start
    layout = parse_map("#####\n#SCG#\n#####\n", "c")
    g = MazeGeometry(layout)
    assert all(g.free[tuple(c)] for c in np.vstack([g.start_cells, g.goal_cells]))


def test_cell_xy_round_trip():
    g = MazeGeometry(make_spec("maze-tight").scene.maze)
    cells = np.argwhere(np.ones((15, 15), bool))
    xy = g.cell_to_xy(cells)
    assert np.allclose(g.cell_to_xy([7, 7]), [0, 0]) and np.allclose(g.cell_to_xy([1, 13]), [6, 6])
    np.testing.assert_array_equal(g.xy_to_cell(xy), cells)


def test_collision_just_inside_and_outside_a_wall():
    spec = make_spec("maze-tight")
    r, eps = BALL_RADIUS, 1e-4
    # the top ring wall covers y in [2.5, 3.5] for x in [-3.5, -0.5]; the 1-cell gap is x in [-0.5, 0.5]
    pts = np.array(
        [
            [-2.0, 3.0],  # deep inside the wall
            [-2.0, 2.5 - r + eps],  # ball just overlapping the wall face
            [-2.0, 2.5 - r - eps],  # ball just clear of it
            [0.5 - r - eps, 3.0],  # in the gap, just clear of its right edge
            [0.5 - r + eps, 3.0],  # in the gap, just touching the right edge
            [0.0, 3.0],  # centre of the gap
            [0.0, 0.0],  # centre of the maze
            [7.6, 0.0],  # outside the map
        ]
    )
    states = np.concatenate([pts, np.zeros((len(pts), 2))], axis=1)
    expected = [True, True, False, False, True, False, False, True]
    assert in_boxes(states, spec.obstacles).tolist() == expected
    # batched plans (P, H, D) give the same answers, and the family's test is this one
    assert in_boxes(states.reshape(2, 4, 4), spec.obstacles).ravel().tolist() == expected
    assert family_of(spec).in_collision(spec, states).tolist() == expected


def test_box_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    centers, halves = rng.normal(size=(5, 2)), rng.uniform(0.1, 1, size=(5, 2))
    pts = rng.normal(size=(200, 2)) * 2
    d = box_distance(pts, centers, halves)
    # brute force: densely sample each box and take the nearest sample
    grid = np.linspace(-1, 1, 201)
    samples = np.concatenate(
        [c + np.stack(np.meshgrid(grid * h[0], grid * h[1]), -1).reshape(-1, 2) for c, h in zip(centers, halves)]
    )
    brute = np.linalg.norm(pts[:, None] - samples[None], axis=-1).min(1)
    assert np.all(d <= brute + 1e-9) and np.all(brute - d < 0.01)


def test_bfs_and_stock_envs():
    g = MazeGeometry(make_spec("maze-tight").scene.maze)
    d = g.bfs((7, 7))
    assert d[7, 7] == 0 and d[4, 7] == 3 and d[1, 13] > 0 and d[0, 0] == -1
    ids = [e["id"] for e in list_envs()]
    assert ids[:2] == ["maze", "maze-tight"]
    spec = make_spec("maze")
    assert spec.horizon == 168 and spec.plan_stride == 2 and spec.success_radius == 0.45


def _random_grid(rng, sizes: tuple[int, int], wall: float, marks: int, min_free: int = 2):
    """A random map's cells: walls with probability ``wall``, up to ``marks`` free cells marked S, G or C, and a
    start and a goal at the first and last free cells; None when fewer than ``min_free`` cells are free."""
    h, w = rng.integers(*sizes, 2)
    g = np.where(rng.random((h, w)) < wall, "#", ".")
    free = np.argwhere(g == ".")
    if len(free) < min_free:
        return None
    for c in free[rng.choice(len(free), min(marks, len(free)), replace=False)]:
        g[tuple(c)] = rng.choice(["S", "G", "C"])
    g[tuple(free[0])], g[tuple(free[-1])] = "S", "G"
    return g


def test_longest_start_goal_path_against_a_search_from_each_goal():
    """The longest start-to-goal grid distance (and from any free cell) as its definition gives it: the largest
    finite distance of a breadth-first search from each goal cell, over random maps with walls, several starts
    and goals, and cells that reach no goal."""
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(60):
        g = _random_grid(rng, (3, 12), 0.3, 4)
        if g is None:
            continue
        try:
            m = MazeGeometry(parse_map("\n".join("".join(r) for r in g), "t"))
        except BadInput:  # no start reaches a goal: refused
            continue
        for anywhere in (False, True):
            starts = np.argwhere(m.free) if anywhere else m.start_cells
            want = max(int(max(m.bfs(goal)[tuple(starts.T)].max(), 0)) for goal in m.goal_cells)
            assert m.longest_start_goal_path(anywhere) == want
        checked += 1
    assert checked > 30


def test_detour_pairs_against_a_search_from_each_goal():
    """The pairs whose shortest path a map lengthens (or cuts) against its trained map, as the definition gives
    them from one breadth-first search per goal cell in each map, over random maps with walls added."""
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(40):
        g = _random_grid(rng, (4, 11), 0.2, 5, min_free=6)
        if g is None:
            continue
        blocked = g.copy()
        plain = np.argwhere(g == ".")
        for c in plain[rng.choice(len(plain), min(3, len(plain)), replace=False)] if len(plain) else []:
            blocked[tuple(c)] = "#"
        try:
            trained = MazeGeometry(parse_map("\n".join("".join(r) for r in g), "t"))
            here = MazeGeometry(parse_map("\n".join("".join(r) for r in blocked), "t"))
        except BadInput:
            continue
        want = [
            [*s, *goal]
            for goal in here.goal_cells
            for s in here.start_cells
            if (s != goal).any()
            and here.bfs(goal)[tuple(s)] >= 0
            and (trained.bfs(goal)[tuple(s)] < 0 or here.bfs(goal)[tuple(s)] > trained.bfs(goal)[tuple(s)])
        ]
        assert here.detour_pairs(trained).tolist() == want
        checked += bool(want)
    assert checked > 5


def test_unknown_env():
    with pytest.raises(BadInput, match="unknown environment"):
        make_spec("moon")


def test_making_a_maze_env_leaves_no_file_in_the_temp_folder(tmp_path, monkeypatch):
    """gymnasium-robotics writes each maze's MuJoCo XML to the temp folder and keeps it; cdrb removes it once the
    model is compiled, so thousands of evals leave nothing behind (and the env still steps)."""
    import tempfile

    from cdrb_cli.envs.family import Episode
    from cdrb_cli.envs.pointmaze.env import PointMaze, training_env

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", None)  # read TMPDIR again
    spec = make_spec("maze-tight")
    env = PointMaze(spec)
    env.reset(Episode(0, (1, 1), (3, 3)))
    env.step(np.zeros(2))
    env.close()
    training_env(spec, seed=0).close()
    assert list(tmp_path.iterdir()) == []


def test_start_goal_pairs_are_drawn_when_most_start_cells_are_sealed_off():
    """A map whose start region is mostly a sealed pocket: rejection sampling alone fails (1 valid start in
    2,401), and the exact draw that follows it gives the same distribution, uniform over the valid pairs."""
    pocket = ["#" + "S" * 60 + "#...#" for _ in range(40)]
    rows = ["#" * 66, *pocket[:-2], "#" + "S" * 60 + "#.S.#", "#" + "S" * 60 + "#G.G#", "#" * 66]
    geom = MazeGeometry(parse_map("\n".join(rows), "pocket"))
    assert len(geom.start_cells) == 2401 and len(geom.goal_cells) == 2
    draws = [geom.draw_start_goal(np.random.default_rng(seed)) for seed in range(40)]
    for s, g in draws:
        assert tuple(s) == (39, 63) and geom.bfs(g)[tuple(s)] >= 0
    goals = [tuple(g) for _, g in draws]
    assert 8 <= goals.count((40, 62)) <= 32  # both goals, about evenly (p = 1/2 each; 40 draws)


def test_a_map_name_with_a_line_break_is_refused():
    """A map's name is printed in log lines: a line break would split them (other control characters are shown
    as ?, by the printer)."""
    for name in ["two\nlines", "a\rb", "a\u2028b"]:
        with pytest.raises(BadInput, match="has a line break"):
            parse_map("#####\n#S.G#\n#####\n", name)
    for name in ["ünïcode name", "x\x1b[31m"]:
        assert parse_map("#####\n#S.G#\n#####\n", name).name == name


def test_a_map_name_with_a_plus_is_refused_so_no_map_shares_an_id_with_a_map_in_a_scene(tmp_path):
    """`map:a+b` names map a in scene b: a map named a+b would share that id (and the folders and rows keyed by
    it), so a map file with a '+' in its name is refused (artifacts made before from such a file still load)."""
    from cdrb_cli.envs.pointmaze.maze import MazeLayout
    from cdrb_cli.envs.registry import family_of, make_spec

    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("#####\n#S.G#\n#...#\n#####\n")
    b.write_text("#####\n#S.G#\n#.#.#\n#####\n")
    spec = make_spec(None, a)
    assert family_of(spec).with_map(spec, b).id == "map:a+b"
    plus = tmp_path / "a+b.txt"
    plus.write_text(a.read_text())
    with pytest.raises(BadInput, match=r"has a '\+'") as err:
        make_spec(None, plus)
    assert "a+b.txt" in str(err.value) and "rename the file" in err.value.hint
    assert MazeLayout(name="a+b", rows=["#####", "#S.G#", "#####"]).name == "a+b"


def test_the_experts_clearance_test_equals_measuring_every_wall_and_large_maps_smooth_quickly(tmp_path):
    """The expert's segment test skips segments with a sample in a wall cell and walls far from the segment: the
    same answer as the distance to every wall box, on random segments; so a 99 x 99 serpentine map (a 4,801-cell
    route) is smoothed into waypoints joined by clear segments (it took hours measuring every box everywhere)."""
    from cdrb_cli.envs.geometry import box_distance
    from cdrb_cli.envs.pointmaze.expert import MazeExpert, PlannerExpertConfig
    from cdrb_cli.envs.pointmaze.maze import MazeLayout

    rng = np.random.default_rng(0)
    maps = [["...#", "...#", "..S.", "..G#", "...#"], ["#####", "#S..#", "#.#.#", "#..G#", "#####"]]
    for rows, size in [(m, s) for m in maps for s in (1.0, 0.3, 0.7, 1.1)]:  # one without a wall border
        ex = MazeExpert.__new__(MazeExpert)  # the route tests on a layout of its own cell size
        ex.cfg, ex.geom = PlannerExpertConfig(), MazeGeometry(MazeLayout(name="m", rows=rows, cell_size=size))
        ex.centers, ex.halves = ex.geom.wall_boxes
        cells = np.argwhere(np.ones((len(rows) + 1, len(rows[0]) + 1), bool)) - 0.5  # corners, off the map too
        spots = np.concatenate(
            [ex.geom.cell_to_xy(cells), ex.geom.cell_to_xy(cells + 0.5), ex.geom.cell_to_xy(cells + [0, 0.5])]
        )
        for _ in range(400):
            a, b = spots[rng.integers(len(spots), size=2)]  # on cell centres, corners and edges: the ties
            clearance = float(rng.choice([0.0, 1e-12, size / 2, size, 0.3]))
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / 0.05)) + 1)
            pts = a[None] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None]
            truth = bool(box_distance(pts, ex.centers, ex.halves).min() >= clearance)
            assert ex._segment_clear(a, b, clearance) == truth, (rows, size, a, b, clearance)
    n = 99
    rows = ["#" * n]
    for i in range(1, n - 1):
        gap = n - 2 if i % 4 == 2 else 1
        rows.append("#" + "." * (n - 2) + "#" if i % 2 else "#" * gap + "." + "#" * (n - gap - 1))
    rows.append("#" * n)
    rows[1], rows[n - 2] = "#S" + rows[1][2:], rows[n - 2][: n - 2] + "G#"
    path = tmp_path / "serpent.txt"
    path.write_text("\n".join(rows) + "\n")
    ex = MazeExpert(make_spec(None, path))
    s, g = ex.geom.start_cells[0], ex.geom.goal_cells[0]  # the route's waypoints, each joined by a clear segment
    ex.reset(np.r_[ex.geom.cell_to_xy(s), 0, 0], ex.geom.cell_to_xy(g), rng)
    assert len(ex.cells) > 4000 and 50 < len(ex.waypoints) < 400
    clear = [
        box_distance(np.linspace(p, q, 200), ex.centers, ex.halves).min() >= 0.3
        for p, q in zip(ex.waypoints[:-1], ex.waypoints[1:])
    ]
    assert all(clear)


def test_a_map_saved_by_a_windows_editor_reads_as_the_same_map(tmp_path):
    from cdrb_cli.envs.pointmaze.maze import load_map_file

    text = "#####\n#S.G#\n#####\n"
    (tmp_path / "unix.txt").write_text(text)
    (tmp_path / "win.txt").write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    assert load_map_file(tmp_path / "win.txt").rows == load_map_file(tmp_path / "unix.txt").rows


def test_a_map_record_without_a_start_goal_pair_is_refused_however_it_was_made():
    """A map edited inside an artifact never passed the file parser: the record itself refuses what the protocol
    cannot draw pairs on (no start, no goal, no start reaching another goal cell)."""
    from pydantic import ValidationError

    from cdrb_cli.envs.pointmaze.maze import MazeLayout

    for rows, needle in [
        (["#####", "#..G#", "#####"], "no start cell"),
        (["#####", "#S..#", "#####"], "no goal cell"),
        (["#####", "#S#G#", "#####"], "reaches a goal cell"),
        (["#####", "#C###", "#####"], "reaches a goal cell"),  # its only goal is itself
    ]:
        with pytest.raises(ValidationError, match=needle):
            MazeLayout(name="x", rows=rows)
    assert MazeLayout(name="x", rows=["#####", "#S.G#", "#####"]).rows[1] == "#S.G#"


def test_every_map_reader_refuses_a_settings_file_and_envs_shows_the_rows_to_copy(tmp_path):
    """A .toml or .json file is a scene or settings file, never a map, whichever command reads it (collect and envs
    as plan's scene does); the rows a new scene starts from are in `cdrb envs --json`, as the hints say."""
    from cdrb_cli.envs.pointmaze.maze import load_map_file

    for name in ("x.toml", "x.JSON"):
        (tmp_path / name).write_text("#####\n#S.G#\n#####\n")
        with pytest.raises(BadInput, match=r"--maze-map .*: a settings file \(\.(toml|JSON)\), not a map"):
            load_map_file(tmp_path / name)
    (tmp_path / "x.txt").write_text("#####\n#S.G#\n#####\n")
    assert load_map_file(tmp_path / "x.txt").rows == ["#####", "#S.G#", "#####"]
    rows = {e["id"]: e.get("rows") for e in list_envs()}
    assert rows["maze-tight"] == make_spec("maze-tight").scene.maze.rows
