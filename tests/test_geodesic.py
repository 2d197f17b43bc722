"""Geodesic buffer balls, checked against their definition: the transition graph joins only consecutive states of
one demonstration; a ball holds the buffer states within eps along the graph (never across a wall the demos did not
cross, never in another component) and a draw is uniform over it."""

from __future__ import annotations

import heapq

import numpy as np
import pytest
from scipy.stats import chisquare

from cdrb_cli.buffer import BallSampler
from cdrb_cli.geodesic import GeodesicBalls, graph_summary, transition_graph


def _u_routes(n: int = 21, gap: float = 0.3):
    """Two demonstrations on either side of a thin wall along y = gap/2 from x = 0 to 0.9: the first runs along
    y = 0 to x = 1 and turns up round the wall's end, the second runs back along y = gap. Buffer: every state."""
    xs = np.linspace(0.0, 1.0, n)
    a = np.stack([xs, np.zeros(n)], axis=1)
    turn = np.array([[1.0, gap / 2], [1.0, gap]])
    b = np.stack([xs[::-1], np.full(n, gap)], axis=1)
    states = np.concatenate([a, turn, b])
    episode = np.repeat([0, 1], [n + 2, n])
    points = np.unique(states, axis=0)
    return points, states, episode


def _reference_ball(points, edges, weights, x, radius):
    """The geodesic ball by its definition, computed another way: Dijkstra in pure Python from the query's nearest
    buffer point, the query's step to it counted first."""
    d_anchor = np.linalg.norm(points - x, axis=1)
    a = int(np.argmin(d_anchor))
    adj = {i: [] for i in range(len(points))}
    for (i, j), w in zip(edges.tolist(), weights.tolist()):
        adj[i].append((j, w))
        adj[j].append((i, w))
    dist = {a: d_anchor[a]}
    heap = [(d_anchor[a], a)]
    while heap:
        d, i = heapq.heappop(heap)
        if d > dist.get(i, np.inf):
            continue
        for j, w in adj[i]:
            if d + w < dist.get(j, np.inf):
                dist[j] = d + w
                heapq.heappush(heap, (d + w, j))
    return np.array(sorted(j for j, d in dist.items() if d < radius), dtype=np.int64)


def test_the_graph_joins_only_consecutive_states_of_one_demonstration_and_is_deterministic():
    points = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 5.0]])
    # demo 0 visits 0 -> 0 -> 1 -> 2 (a repeat is no edge); demo 1 stays near 3; the step from demo 0's last
    # state to demo 1's first is no edge
    states = np.array([[0.1, 0.0], [0.0, 0.1], [0.9, 0.0], [2.1, 0.1], [0.0, 4.9], [0.1, 5.0]])
    episode = np.array([0, 0, 0, 0, 1, 1])
    edges, weights = transition_graph(points, states, episode)
    assert edges.tolist() == [[0, 1], [1, 2]] and np.allclose(weights, [1.0, 1.0])
    again = transition_graph(points, states, episode)
    assert np.array_equal(again[0], edges) and np.array_equal(again[1], weights)
    summary = graph_summary(len(points), edges)
    assert summary["components"] == 2 and summary["isolated_nodes"] == 1 and summary["max_degree"] == 2


def test_states_join_the_graph_by_position_so_a_velocity_never_pulls_one_across_a_wall():
    """Nearest in every feature, a state by a thin wall (x = 0.5) moving like the buffer point across it joins that
    point, and the graph gets an edge across the wall; nearest by position (the family's position dims) it joins the
    point on its own side, as the demonstration's path did."""
    # buffer points (x, y, vx, vy): two on the left of the wall, one on the right moving like the demo
    points = np.array([[0.0, 0.0, 0.0, 0.0], [0.4, 0.0, 0.0, 0.0], [0.6, 0.0, 1.0, 0.0]])
    # one demonstration on the left: from point 0 towards the wall, arriving fast at x = 0.45
    states = np.array([[0.0, 0.0, 0.0, 0.0], [0.45, 0.0, 1.0, 0.0]])
    episode = np.array([0, 0])
    assert transition_graph(points, states, episode)[0].tolist() == [[0, 2]]  # across the wall
    assert transition_graph(points, states, episode, [0, 1])[0].tolist() == [[0, 1]]
    from cdrb_cli.envs.registry import family_of, make_spec

    maze, push = make_spec("maze-tight"), make_spec("fetch-push-obstacle")
    assert family_of(maze).position_dims(maze) == [0, 1]
    assert family_of(push).position_dims(push) == [0, 1, 2, 3, 4, 5]  # the gripper's and the block's


def test_a_geodesic_ball_never_reaches_across_a_wall_the_demos_went_round():
    """Beside the wall's far end the Euclidean ball draws states from the other side of the wall; the geodesic ball
    of the same radius never does, at any radius shorter than the way round."""
    points, states, episode = _u_routes()
    edges, weights = transition_graph(points, states, episode)
    geo, euc = GeodesicBalls(points, edges, weights), BallSampler(points, np.array([0.0, 0.5]))
    rng = np.random.default_rng(0)
    x = np.repeat([[0.1, 0.0]], 4000, axis=0)  # on the first route, 0.3 from the second across the wall
    # the other route beside the query: the way round to it from x = 0.1 is at least 0.9 + 0.3 + 0.5 = 1.7
    other_side = lambda idx: (points[idx[idx >= 0], 1] > 0.2) & (points[idx[idx >= 0], 0] < 0.5)  # noqa: E731
    for radius in (0.35, 0.5, 1.0, 1.6):
        assert not other_side(geo.sample(x, np.full(len(x), radius), rng)).any(), radius
        assert other_side(euc.sample(x, np.full(len(x), radius), rng)).any(), radius
    assert other_side(geo.sample(x, np.full(len(x), 2.5), rng)).any()  # beyond the way round it may


@pytest.mark.parametrize("radius", [0.12, 0.45, 1.4, 2.3])
def test_geodesic_draws_are_uniform_over_the_ball_by_its_definition(radius):
    points, states, episode = _u_routes(n=15)
    edges, weights = transition_graph(points, states, episode)
    geo = GeodesicBalls(points, edges, weights)
    x = np.array([0.33, 0.04])  # off the buffer: attached through its nearest point
    ball = _reference_ball(points, edges, weights, x, radius)
    assert np.array_equal(geo.members(x, radius), ball)
    draws = geo.sample(np.repeat(x[None], 30_000, axis=0), np.full(30_000, radius), np.random.default_rng(1))
    assert set(np.unique(draws).tolist()) == set(ball.tolist())
    counts = np.bincount(draws, minlength=len(points))[ball]
    assert chisquare(counts).pvalue > 1e-3


def test_other_components_and_queries_far_from_the_buffer():
    """A ball never holds a state of another component, however large; a query farther from its nearest buffer
    state than the radius has an empty ball (-1: the state is kept, as for an empty Euclidean ball)."""
    points = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [0.3, 0.05], [0.4, 0.05]])
    states = points.copy()
    episode = np.array([0, 0, 0, 1, 1])
    edges, weights = transition_graph(points, states, episode)
    geo = GeodesicBalls(points, edges, weights)
    draws = geo.sample(np.repeat([[0.05, 0.0]], 2000, axis=0), np.full(2000, 100.0), np.random.default_rng(2))
    assert set(draws.tolist()) == {0, 1, 2}
    far = geo.sample(np.array([[0.0, 1.0], [0.0, 0.5]]), np.array([0.9, 0.6]), np.random.default_rng(3))
    assert far[0] == -1 and far[1] == 0  # 1.0 from its anchor with radius 0.9: empty; 0.5 < 0.6: the anchor


def test_cluster_writes_the_graph_inspect_shows_it_and_an_older_buffer_says_it_has_none(
    tmp_path, small_data, cdrb, monkeypatch
):
    """`cdrb cluster` stores the transition graph of its demos (the same as built from them again); `cdrb inspect
    --json` counts it; a buffer written without one reads, and asking it for the graph is one line on how to get
    one."""
    import json

    import h5py

    from cdrb_cli import artifacts
    from cdrb_cli.buffer import Normalizer, demo_features, split_rows
    from cdrb_cli.errors import BadInput

    demos, buffer = small_data
    edges, weights = buffer.graph()
    norm = Normalizer(buffer.low, buffer.high)
    rows = split_rows(demos, buffer.manifest.config.split)
    episode = np.concatenate([np.full(n, i) for i, n in enumerate(demos.episode_length)])
    z = norm.normalize(demo_features(demos, buffer.manifest.config.features)[rows])
    assert buffer.manifest.config.graph_join == "features"  # states join at the nearest point in every feature
    again = transition_graph(buffer.points, z, episode[rows])
    assert np.array_equal(edges, again[0]) and np.allclose(weights, again[1]) and len(edges) >= len(buffer.points) - 1
    info = json.loads(cdrb("inspect", buffer.path, "--json").stdout)
    assert info["graph"] == graph_summary(len(buffer.points), edges)
    old = tmp_path / "old.h5"
    arrays = {k: v for k, v in buffer.arrays.items() if not k.startswith("graph/")}
    manifest = buffer.manifest.model_copy(update={"schema_version": "2.6"})
    with monkeypatch.context() as m:  # written as a buffer of before the graph
        m.setitem(artifacts.SCHEMA_VERSIONS, "buffer", "2.6")
        artifacts.save(old, "buffer", manifest, arrays)
    with h5py.File(old) as f:
        assert "graph" not in f
    assert artifacts.load(old, "buffer").manifest.config.graph_join == "features"
    # `--graph-join position`: states join at the nearest buffer state by x, y
    r = cdrb("cluster", demos.path, "--k", "100", "--graph-join", "position", "--out", tmp_path / "pos.h5")
    assert r.returncode == 0, r.stderr
    pos = artifacts.load(tmp_path / "pos.h5", "buffer")
    assert pos.manifest.config.graph_join == "position"
    np.testing.assert_array_equal(pos.points, buffer.points)
    assert np.array_equal(pos.graph()[0], transition_graph(buffer.points, z, episode[rows], [0, 1])[0])
    r = cdrb("cluster", demos.path, "--graph-join", "x-y", "--out", tmp_path / "bad.h5")
    assert r.returncode == 2 and "features" in r.stderr and not (tmp_path / "bad.h5").exists()
    with pytest.raises(BadInput, match="has no transition graph.*cdrb cluster"):
        artifacts.load(old, "buffer").graph()
    # the buffer picture draws the graph's edges; a buffer without one draws its states alone
    from matplotlib.image import imread

    from cdrb_cli.envs.render import plot_buffer

    with_graph = imread(plot_buffer(buffer, tmp_path / "with.png"))
    without = imread(plot_buffer(artifacts.load(old, "buffer"), tmp_path / "without.png"))
    assert with_graph.shape == without.shape and not np.array_equal(with_graph, without)


def _pair_counts(points, edges, weights):
    """Every ordered pair's Euclidean and graph distance (i = j included), from dense matrices (another way than
    the sampler's sorted tables)."""
    from scipy.sparse.csgraph import shortest_path

    k = len(points)
    adj = np.zeros((k, k))
    for (i, j), w in zip(edges.tolist(), weights.tolist()):
        adj[i, j] = adj[j, i] = w
    return np.linalg.norm(points[:, None] - points[None], axis=-1).ravel(), shortest_path(adj, directed=False).ravel()


def _two_u_routes(shift: float = 0.5):
    """Two copies of :func:`_u_routes`, ``shift`` apart along y: two components of the graph."""
    points, states, episode = _u_routes(n=31)
    far = points + [0.0, shift]
    return (
        np.concatenate([points, far]),
        np.concatenate([states, states + [0.0, shift]]),
        np.concatenate([episode, episode + 2]),
    )


@pytest.mark.parametrize(
    "schedule, T, routes",
    [("linear", 12, 1), ("log", 12, 1), ("geometric", 12, 1), ("linear", 128, 1), ("linear", 12, 2)],
)
def test_matched_geodesic_radii_hold_as_many_buffer_pairs_as_the_papers_balls(schedule, T, routes):
    """Each step's geodesic radius is the least r >= the paper's Euclidean radius whose balls around the buffer
    states hold together as many members as the paper's balls of that step hold among pairs of one component; the
    last is d_max. At T = 128 the first Euclidean balls hold no neighbour of a buffer state, yet the geodesic radius
    stays the Euclidean one (not 0: a query off the buffer still finds its neighbour); with two components the
    radii do not jump to d_max. The scaled radii (the schedule over the graph's diameter) hold more at the first
    step."""
    from cdrb_cli.buffer import radii

    points, states, episode = _u_routes(n=31) if routes == 1 else _two_u_routes()
    edges, weights = transition_graph(points, states, episode)
    geo = GeodesicBalls(points, edges, weights)
    euc, graph = _pair_counts(points, edges, weights)
    same = np.isfinite(graph)  # pairs of one component
    last = np.nextafter(graph[same].max(), np.inf)  # d_max: every pair of one component strictly inside
    eps = geo.matched_radii(radii(schedule, 1.0, T), last)
    reference = radii(schedule, euc.max(), T)
    assert eps[0] == 0 and eps[-1] == last and np.all(np.diff(eps) >= 0)
    for k in range(1, T - 1):
        wanted = int(((euc < reference[k]) & same).sum())
        assert eps[k] >= reference[k] > 0 and int((graph < eps[k]).sum()) >= wanted, k
        least = eps[k] == reference[k] or int((graph < np.nextafter(eps[k], 0)).sum()) < wanted
        assert least, k
    if routes == 2:  # where the paper's balls first hold more pairs than the graph joins, the radii still grow
        k = next(k for k in range(1, T) if (euc < reference[k]).sum() > same.sum())
        assert eps[k] < eps[k + 1] < last
    if T == 128:
        assert (euc[euc > 0] >= reference[1]).all() and eps[1] == reference[1]
    scaled = radii(schedule, last, T)
    assert (graph < scaled[1]).sum() > (euc < reference[1]).sum() or T == 128  # at 128 both: themselves
    smaller = geo.matched_radii(radii(schedule, 1.0, T), 0.5)  # a d_max set below the matched radii cuts them
    assert smaller[-1] == 0.5 and smaller.max() == 0.5 and np.array_equal(smaller, np.minimum(eps, 0.5))


def test_cdrb_with_geodesic_balls_trains_plans_and_degrades_only_within_them(tmp_path, small_data, cdrb):
    """`--set method.ball=geodesic`: the model carries the buffer's graph, every degradation of training and of
    sampling replaces a state by a member of its geodesic ball, and plans come out; a tampered graph in the model is
    one line; a buffer without a graph is refused before training."""
    import torch

    from cdrb_cli import artifacts
    from cdrb_cli.methods.checkpoint import load_method
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.factories import tampered
    from tests.test_train import tiny

    demos, buffer = small_data
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=10, **{"method.ball": "geodesic"}))
    model = train(demos, buffer, cfg, tmp_path / "geo.h5")
    assert np.array_equal(model.arrays["buffer/graph/edges"], buffer.graph()[0])
    method = load_method(model)
    ball = method.ball
    assert isinstance(ball, GeodesicBalls)
    # matched radii by default, the same ones when the model is loaded again; the last ball holds the buffer whole
    from cdrb_cli.buffer import radii

    p = method.config.method
    assert p.geodesic_radii == "matched" and method.eps[-1] == p.d_max
    assert np.array_equal(method.eps, ball.matched_radii(radii(p.schedule, 1.0, method.T), p.d_max))
    assert np.array_equal(load_method(artifacts.load(model.path, "model")).eps, method.eps)
    rng = np.random.default_rng(0)
    x = torch.from_numpy(ball.random_states((6, method.horizon), rng).astype(np.float32))
    x[:, :, :2] += 0.05  # off the buffer: attached through the nearest point
    inner = slice(1, -1) if method.kept else slice(None)  # the pinned ends are not degraded
    for k in (1, 3, method.T - 2):
        y = method._degrade(x, np.full(6, k), rng).numpy()[:, inner].reshape(-1, x.shape[-1])
        for q, r in zip(x.numpy()[:, inner].reshape(-1, x.shape[-1]), y):
            members = ball.members(q.astype(np.float64), method.eps[k])
            moved = not np.allclose(q, r)
            assert (not moved and members.size == 0) or any(np.allclose(r, ball.points[j]) for j in members)
    r = cdrb("plan", model.path, "--pairs", "3", "--out", tmp_path / "p.h5")
    assert r.returncode == 0, r.stderr
    assert artifacts.load(tmp_path / "p.h5", "plans").arrays["plans"].shape[0] == 3
    bad = tmp_path / "bad.h5"
    bad.write_bytes(model.path.read_bytes())
    with tampered(bad) as f:  # an edge to a point that does not exist
        e = f["buffer/graph/edges"][()]
        e[0, 1] = len(buffer.points) + 5
        del f["buffer/graph/edges"]
        f["buffer/graph/edges"] = e
    r = cdrb("plan", bad, "--pairs", "1", "--out", tmp_path / "q.h5")
    assert r.returncode == 2 and "buffer/graph/edges must join two distinct points" in r.stderr, r.stderr


def test_the_last_geodesic_ball_holds_the_whole_buffer_by_default(small_data):
    """d_max defaults to the buffer's diameter in the measure the balls use: along the graph for geodesic balls
    (its Euclidean diameter would leave far states out of every ball, while sampling starts from all of them)."""
    from cdrb_cli.geodesic import graph_diameter
    from cdrb_cli.methods.config import train_config

    demos, buffer = small_data
    s = buffer.manifest.summary
    assert s.graph_diameter == pytest.approx(graph_diameter(len(buffer.points), *buffer.graph()), abs=1e-5)
    assert s.graph_diameter > s.diameter
    assert train_config(demos, buffer, "cdrb", {"method.ball": "geodesic"}).method.d_max == s.graph_diameter
    assert train_config(demos, buffer, "cdrb", {}).method.d_max == s.diameter
    mine = {"method.ball": "geodesic", "method.d_max": 1.5}
    assert train_config(demos, buffer, "cdrb", mine).method.d_max == 1.5


def test_a_masked_geodesic_buffer_loses_the_removed_states_edges_and_each_mask_starts_whole(tmp_path, small_data):
    """A new obstacle at plan time removes buffer states: their edges go with them (a path through them is gone),
    and a second mask (another scene) starts again from the whole buffer, not from the first mask's."""
    from cdrb_cli.methods.checkpoint import load_method
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=2, **{"method.ball": "geodesic"}))
    method = load_method(train(demos, buffer, cfg, tmp_path / "geo.h5"))
    whole, points = method.ball, method.points
    cut = float(np.median(points[:, 0]))
    removed = points[:, 0] > cut
    counts = method.mask(lambda f: np.asarray(f)[..., 0] > cut)
    assert counts == {"buffer_states": len(points), "removed": int(removed.sum())}
    masked = method.ball
    assert np.array_equal(masked.points, whole.points[~removed])
    both = ~removed[whole.edges[:, 0]] & ~removed[whole.edges[:, 1]]
    assert 0 < len(masked.edges) == int(both.sum()) < len(whole.edges)
    method.mask(lambda f: np.zeros(np.asarray(f).shape[:-1], dtype=bool))
    assert len(method.ball.points) == len(points) and len(method.ball.edges) == len(whole.edges)


def test_report_keeps_geodesic_and_euclidean_cdrb_apart(tmp_path, small_data, tiny_models, cdrb):
    """Evals of a CDRB model with geodesic balls record it (summary.variant), so `cdrb report` gives it its own row
    beside the paper's CDRB on the same pairs instead of refusing two evals of one method and seed."""
    import json

    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=2, **{"method.ball": "geodesic"}))
    geo = train(demos, buffer, cfg, tmp_path / "geo.h5")
    for name, model in (("geo", geo.path), ("euc", tiny_models["cdrb"].path)):
        r = cdrb("eval", model, "-n", "2", "--seeds", "0", "--out", tmp_path / f"eval-{name}.h5")
        assert r.returncode == 0, r.stderr
    r = cdrb("report", tmp_path / "eval-geo.h5", tmp_path / "eval-euc.h5", "--format", "json")
    assert r.returncode == 0, r.stderr
    assert sorted(row["method"] for row in json.loads(r.stdout)) == ["cdrb", "cdrb [geodesic balls]"]
