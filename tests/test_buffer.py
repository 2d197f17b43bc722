"""The replay buffer and the degradation D: exactness (uniform over ball ∩ buffer), pinning, schedules,
normalizer, k-means snapping."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chisquare

from cdrb_cli.buffer import BallSampler, Normalizer, TorchBallSampler, diameter, kmeans_buffer, radii


class TorchOnNumpy:
    """The torch sampler behind the numpy sampler's interface, so every exactness test below runs on both."""

    def __init__(self, points, eps, strategy="auto"):
        self.t = TorchBallSampler(points, eps, strategy={"brute": "dense"}.get(strategy, strategy))

    def sample(self, x, radius, rng):
        import torch

        return self.t.sample(torch.as_tensor(x), torch.as_tensor(radius), self.t.generator(rng)).numpy()

    def degrade(self, traj, k, rng, pinned=(0, -1)):
        import torch

        return self.t.degrade(torch.as_tensor(traj), k, self.t.generator(rng), pinned=pinned).numpy()


SAMPLERS = {"numpy": BallSampler, "torch": TorchOnNumpy}


def _inside(points, x, r):
    return np.flatnonzero(((points - x) ** 2).sum(1) < r * r)


def _check_uniform(idx, points, x, r):
    inside = _inside(points, x, r)
    assert len(inside) >= 5, "test set-up: the ball should hold several points"
    drawn = idx[idx >= 0]
    assert len(drawn) == len(idx), "a non-empty ball must always give a buffer point"
    outside = np.setdiff1d(np.unique(drawn), inside)
    assert outside.size == 0, f"drew points outside the ball: {outside}"
    counts = np.bincount(drawn, minlength=len(points))[inside]
    assert counts.min() > 0
    p = chisquare(counts).pvalue
    assert p > 1e-3, f"draws are not uniform over ball ∩ buffer (chi-square p={p:.2g}, counts {counts})"


@pytest.mark.parametrize("impl", SAMPLERS)
@pytest.mark.parametrize("strategy", ["auto", "brute"])
@pytest.mark.parametrize("radius", [0.35, 0.6, 1.5])
def test_ball_draws_are_uniform_over_ball_and_buffer(impl, strategy, radius):
    rng = np.random.default_rng(1)
    points = rng.uniform(-1, 1, size=(300, 3))
    x = np.array([0.1, -0.2, 0.05])
    s = SAMPLERS[impl](points, np.array([0.0, radius]), strategy=strategy)
    n = 30_000
    idx = s.sample(np.repeat(x[None], n, 0), np.full(n, radius), np.random.default_rng(2))
    _check_uniform(idx, points, x, radius)


def test_tree_enumeration_is_exact_when_balls_overflow_k():
    """The KD-tree branch starts with a small k; balls holding more points are enumerated again, wider."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, size=(400, 2))
    x, r = np.array([0.0, 0.0]), 0.5  # ~80 points, more than the first k
    s = BallSampler(points, np.array([0.0, r]))
    n = 20_000
    idx = s._enumerate_tree(np.repeat(x[None], n, 0), np.full(n, r * r), np.random.default_rng(4))
    _check_uniform(idx, points, x, r)


def test_tree_enumeration_decides_points_on_the_sphere_from_differences():
    """Points within rounding of the ball's sphere are inside exactly when their squared difference, summed as the
    sampler's other paths sum it, is below r^2: the tree's own distances decide only points clearly in or out."""
    rng = np.random.default_rng(11)
    x, r = rng.normal(size=3), 0.7
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    points = np.concatenate([x + r * u, x + 0.5 * r * u[:20], x + 2 * r * u[:50]])  # on, inside, outside
    d = points - x
    inside = np.flatnonzero(np.einsum("nd,nd->n", d, d) < r * r)  # the sampler's membership, summed its way
    assert 20 < len(inside) < 420, "test set-up: rounding puts some sphere points inside and some outside"
    s = BallSampler(points, np.array([0.0, r]))
    n = 60_000
    idx = s._enumerate_tree(np.repeat(x[None], n, 0), np.full(n, r * r), np.random.default_rng(12))
    assert set(np.unique(idx).tolist()) == set(inside.tolist())


@pytest.mark.parametrize("impl", SAMPLERS)
def test_mixed_queries_each_uniform(impl):
    rng = np.random.default_rng(5)
    points = rng.uniform(-1, 1, size=(500, 2))
    xs = np.array([[0.3, 0.3], [-0.5, 0.1]])
    rs = np.array([0.25, 0.8])
    n = 20_000
    q = np.repeat(xs, n, 0)
    s = SAMPLERS[impl](points, np.array([0.0, 1.0]))
    draws = [s.sample(q, np.repeat(rs, n), np.random.default_rng(seed)).reshape(2, n) for seed in (6, 7, 8)]
    idx = np.concatenate(draws, axis=1)  # 60,000 draws per ball, from three independent streams
    for i in range(2):
        _check_uniform(idx[i], points, xs[i], rs[i])


@pytest.mark.parametrize("candidates", ["adaptive", "fixed"])
@pytest.mark.parametrize("k", [1, 3, 7])
def test_degrade_at_one_step_is_uniform(k, candidates):
    """Degrading every plan at the same step (how sampling calls it) takes its own path through the sampler: its
    draws too are uniform over ball ∩ buffer, for a small ball (enumerated) and larger ones (rejection first)."""
    rng = np.random.default_rng(9)
    points = rng.uniform(-1, 1, size=(800, 2))
    eps = radii("linear", 1.0, 8)
    s = BallSampler(points, eps, candidates=candidates)
    assert not s._level_big[1] and s._level_big[3] and s._level_big[7]  # the test covers both branches
    x = np.array([0.2, -0.1])
    traj = np.repeat(x[None, None], 40_002, axis=1)  # one plan of 40,000 free states, all at x
    out = s.degrade(traj, k, np.random.default_rng(10))[0, 1:-1]
    lookup = {tuple(p): j for j, p in enumerate(points)}
    idx = np.array([lookup.get(tuple(row), -1) for row in out])
    _check_uniform(idx, points, x, eps[k])


@pytest.mark.parametrize("impl", SAMPLERS)
def test_ball_is_strict_and_empty_ball_keeps_the_state(impl):
    points = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.0], [3.0, 3.0]])
    s = SAMPLERS[impl](points, np.array([0.0, 1.0]))
    idx = s.sample(np.zeros((2000, 2)), np.ones(2000), np.random.default_rng(0))
    assert set(idx.tolist()) == {2}  # points at distance exactly 1 are not strictly inside
    far = np.full((10, 2), -5.0)
    assert (s.sample(far, np.ones(10), np.random.default_rng(0)) == -1).all()
    traj = np.full((1, 4, 2), -5.0)
    np.testing.assert_array_equal(s.degrade(traj, 1, np.random.default_rng(0)), traj)


@pytest.mark.parametrize("impl", SAMPLERS)
def test_degrade_pins_ends_and_step_zero_is_identity(impl):
    rng = np.random.default_rng(7)
    points = rng.uniform(-1, 1, size=(1000, 4))
    eps = radii("linear", 2.0, 16)
    s = SAMPLERS[impl](points, eps)
    traj = rng.uniform(-1, 1, size=(8, 12, 4))
    ks = rng.integers(1, 16, size=8)
    out = s.degrade(traj, ks, rng)
    np.testing.assert_array_equal(out[:, 0], traj[:, 0])
    np.testing.assert_array_equal(out[:, -1], traj[:, -1])
    for b in range(8):
        for h in range(1, 11):
            d = np.linalg.norm(out[b, h] - traj[b, h])
            is_point = np.any(np.all(points == out[b, h], axis=1))
            assert (is_point and d < eps[ks[b]]) or np.array_equal(out[b, h], traj[b, h])
    np.testing.assert_array_equal(s.degrade(traj, 0, rng), traj)
    # same seed, same draws
    a = s.degrade(traj, ks, np.random.default_rng(11))
    b = s.degrade(traj, ks, np.random.default_rng(11))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("impl", SAMPLERS)
def test_large_buffer_path_matches_brute_distribution(impl):
    """K = 20,000 exercises rejection rounds and the KD-tree (numpy) or dense enumeration (torch); both are
    uniform over ball ∩ buffer."""
    rng = np.random.default_rng(8)
    points = rng.normal(size=(20_000, 2)) * 0.5
    x, r = np.array([0.2, 0.1]), 0.03  # a small ball: ~10 points
    s = SAMPLERS[impl](points, np.array([0.0, r]))
    n = 8000
    idx = s.sample(np.repeat(x[None], n, 0), np.full(n, r), np.random.default_rng(9))
    _check_uniform(idx, points, x, r)
    r2 = 0.4  # a big ball: rejection sampling
    idx = s.sample(np.repeat(x[None], 40_000, 0), np.full(40_000, r2), np.random.default_rng(10))
    drawn = idx[idx >= 0]
    assert np.all(np.linalg.norm(points[drawn] - x, axis=1) < r2)
    inside = _inside(points, x, r2)
    counts = np.bincount(drawn, minlength=len(points))[inside]
    # ~3,000 points, ~13 draws each: compare the spread with a multinomial's rather than a full chi-square
    assert abs(counts.mean() - len(drawn) / len(inside)) < 1e-9
    assert 0.7 < counts.var() / counts.mean() < 1.3


@pytest.mark.parametrize("schedule", ["linear", "log", "geometric", "sqrt", "sigmoid"])
def test_schedules(schedule):
    eps = radii(schedule, 3.0, 32)
    assert eps[0] == 0 and np.isclose(eps[-1], 3.0) and np.all(np.diff(eps[1:]) > 0)
    linear = np.arange(32) / 31 * 3.0
    if schedule == "linear":
        np.testing.assert_allclose(eps, linear)
    if schedule == "log":  # the official code's log(linspace(1, T+1, T)), scaled to end at d_max: concave
        np.testing.assert_allclose(eps, np.log(np.linspace(1, 33, 32)) / np.log(33) * 3.0)
        assert np.all(eps[1:-1] > linear[1:-1]) and np.all(np.diff(eps, 2) < 0)
    if schedule == "geometric":  # log-spaced from d_max / 100: convex, most steps use small balls
        assert np.isclose(eps[1], 0.03 * (100 ** (1 / 31))) and np.all(eps[1:-1] < linear[1:-1])
        assert np.all(np.diff(eps[1:], 2) > 0)


def test_normalizer_round_trip_and_constant_feature():
    x = np.array([[0.0, 5.0, 1.0], [2.0, -5.0, 1.0], [1.0, 0.0, 1.0]])
    n = Normalizer.fit(x)
    z = n.normalize(x)
    assert z.min(0)[:2].tolist() == [-1, -1] and z.max(0)[:2].tolist() == [1, 1]
    assert np.all(z[:, 2] == 0)
    np.testing.assert_allclose(n.unnormalize(z), x, atol=1e-6)
    import torch

    torch.testing.assert_close(n.normalize(torch.tensor(x)), torch.tensor(z))


def test_kmeans_snaps_to_real_states_and_diameter():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(3000, 2))
    keep, inertia = kmeans_buffer(pts, 50, seed=0)
    assert len(keep) <= 50 and len(keep) > 40 and inertia > 0
    assert keep.max() < 3000  # indices of real points
    small = pts[:300]
    brute = max(np.linalg.norm(a - b) for a in small for b in small)
    assert np.isclose(diameter(small), brute)


def test_torch_sampler_keeps_dtype_and_pins_for_float32_batches():
    import torch

    rng = np.random.default_rng(12)
    points = rng.uniform(-1, 1, size=(200, 3))
    s = TorchBallSampler(points, radii("linear", 2.0, 8))
    traj = torch.as_tensor(rng.uniform(-1, 1, size=(4, 6, 3)), dtype=torch.float32)
    out = s.degrade(traj, np.array([1, 3, 5, 7]), s.generator(rng))
    assert out.dtype == torch.float32 and out.shape == traj.shape
    assert torch.equal(out[:, 0], traj[:, 0]) and torch.equal(out[:, -1], traj[:, -1])
    pts = torch.as_tensor(points, dtype=torch.float32)
    new, old = out[:, 1:-1].reshape(-1, 3), traj[:, 1:-1].reshape(-1, 3)
    is_point = torch.stack([(pts == row).all(1).any() for row in new])
    kept = (new == old).all(1)
    assert bool((is_point | kept).all()) and int(is_point.sum()) > len(new) // 2  # a buffer point, or an empty ball
    assert s.random_states((2, 5), s.generator(rng)).shape == (2, 5, 3)


@pytest.mark.parametrize("k", [1, 3, 7])
def test_degradation_with_given_uniforms_is_uniform_and_keeps_empty_balls(k):
    """The degradation a CUDA graph holds (static shapes, its uniforms given): the rank floor(u * n) among the n
    points inside each ball is a uniform draw over ball ∩ buffer; an empty ball keeps the state; ends untouched."""
    import torch

    rng = np.random.default_rng(11)
    points = rng.uniform(-1, 1, size=(800, 2))
    eps = radii("linear", 1.0, 8)
    s = TorchBallSampler(points, eps)
    x = np.array([0.2, -0.1])
    n = 40_000
    traj = torch.as_tensor(np.repeat(x[None, None], n + 2, axis=1))
    traj[0, 0] = traj[0, -1] = 9.0  # far from every point: would be kept anyway, and must not be drawn for
    u = torch.as_tensor(np.random.default_rng(12).random((1, n)))
    out = s.degrade_given(traj, eps[k], u, slice(1, n + 1)).numpy()[0]
    assert (out[0] == 9.0).all() and (out[-1] == 9.0).all()
    lookup = {tuple(p): j for j, p in enumerate(points)}
    _check_uniform(np.array([lookup.get(tuple(row), -1) for row in out[1:-1]]), points, x, eps[k])
    far = torch.full((1, 4, 2), -5.0, dtype=torch.float64)
    np.testing.assert_array_equal(s.degrade_given(far, eps[k], torch.rand(1, 2, dtype=torch.float64), slice(1, 3)), far)
