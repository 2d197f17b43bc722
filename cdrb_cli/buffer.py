"""The replay buffer CDRB diffuses through: features, normalizer, k-means with snapping, and the degradation D.

* :class:`Normalizer` maps each feature to [-1, 1] by its min/max over the demonstrations.
* :func:`kmeans_buffer` clusters the buffer and replaces every centroid by its nearest real buffer state, so the
  buffer contains only known good states.
* :class:`BallSampler` is the degradation D(tau, k): every non-pinned state is replaced by a buffer state drawn
  **uniformly from the buffer points strictly inside the ball** of radius eps_k around it (the state is kept when
  that ball is empty). It is exact and never materializes a (queries, K, D) tensor:

  1. *rejection rounds*: ``tries`` uniform buffer indices per query; the first one inside the ball is taken.
     Conditioned on acceptance, a uniform draw is uniform over ball ∩ buffer;
  2. *exact enumeration* for queries with no accepted candidate: brute-force squared distances in query chunks
     (small K) or a KD-tree ball query (large K), then a uniform pick among the points inside.

  Both branches draw from the same uniform distribution with independent randomness, so their mixture is exact.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from cdrb_cli.envs.spec import EnvSpec

SCHEDULES = ("linear", "log", "geometric", "sqrt", "sigmoid")


# ------------------------------------------------------------------------------------------------ features
def feature_dim(spec: EnvSpec, features: str) -> int:
    return spec.obs_dim + (spec.action_dim if features == "state-action" else 0)


def demo_features(demos, features: str) -> np.ndarray:
    """Per-step feature rows of a demos artifact: observations, optionally followed by actions."""
    obs = demos.observations
    if features == "state-action":
        return np.concatenate([obs, demos.actions], axis=1)
    return obs


def split_rows(demos, split: str) -> np.ndarray:
    """Row indices (into the flat step arrays) of the episodes in ``split`` (train / valid / all)."""
    eps = demos.episode_ids(split)
    starts, lengths = demos.episode_start[eps], demos.episode_length[eps]
    if len(eps) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate([np.arange(s, s + n) for s, n in zip(starts, lengths)])


@dataclass(frozen=True)
class Normalizer:
    """Per-feature min/max scaling to [-1, 1]; a constant feature maps to 0."""

    low: np.ndarray
    high: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray) -> Normalizer:
        return cls(low=x.min(axis=0).astype(np.float32), high=x.max(axis=0).astype(np.float32))

    @property
    def center(self) -> np.ndarray:
        return (self.low.astype(np.float64) + self.high) / 2

    @property
    def half(self) -> np.ndarray:
        h = (self.high.astype(np.float64) - self.low) / 2
        return np.where(h > 0, h, 1.0)

    def normalize(self, x):
        return _apply(x, lambda c, h, v: (v - c) / h, self)

    def unnormalize(self, z):
        return _apply(z, lambda c, h, v: v * h + c, self)

    def allclose(self, other: Normalizer, rtol: float = 1e-5) -> bool:
        return (
            self.low.shape == other.low.shape
            and np.allclose(self.low, other.low, rtol=rtol, atol=1e-6)
            and np.allclose(self.high, other.high, rtol=rtol, atol=1e-6)
        )


def _apply(x, fn, norm: Normalizer):
    # a tensor implies torch is imported already: numpy callers (collect, cluster) never pay torch's import
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(x, torch.Tensor):
        c = torch.as_tensor(norm.center, dtype=x.dtype, device=x.device)
        h = torch.as_tensor(norm.half, dtype=x.dtype, device=x.device)
        return fn(c, h, x)
    x = np.asarray(x)
    out = fn(norm.center, norm.half, x.astype(np.float64))
    return out.astype(x.dtype if x.dtype.kind == "f" else np.float64)


# ------------------------------------------------------------------------------------------------ clustering
def kmeans_buffer(
    points: np.ndarray, k: int, seed: int, n_init: int = 1, max_iter: int = 100, fit_sample: int = 100_000
) -> tuple[np.ndarray, float]:
    """Indices of ``k`` real points representing ``points``: k-means (scikit-learn, fitted on at most
    ``fit_sample`` random points), each centroid snapped to its nearest point of the full set (duplicates
    dropped). Returns (sorted unique indices, inertia of the fit)."""
    import warnings

    from scipy.spatial import cKDTree
    from sklearn.cluster import KMeans
    from sklearn.exceptions import ConvergenceWarning

    rng = np.random.default_rng(seed)
    fit = points if len(points) <= fit_sample else points[rng.choice(len(points), fit_sample, replace=False)]
    km = KMeans(n_clusters=k, n_init=n_init, max_iter=max_iter, random_state=seed)
    with warnings.catch_warnings():  # fewer distinct points than k: the caller says so in its own words
        warnings.simplefilter("ignore", ConvergenceWarning)
        km.fit(fit.astype(np.float32))
    _, idx = cKDTree(points).query(km.cluster_centers_.astype(np.float64))
    return np.unique(idx), float(km.inertia_)


def diameter(points: np.ndarray, exact_limit: int = 20_000, chunk: int = 2048) -> float:
    """Largest pairwise Euclidean distance (exact up to ``exact_limit`` points; beyond that the diagonal of the
    bounding box, an upper bound)."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) > exact_limit:
        return float(np.linalg.norm(p.max(0) - p.min(0)))
    sq = (p * p).sum(1)
    best = 0.0
    for a in range(0, len(p), chunk):
        q = p[a : a + chunk]
        d2 = (q * q).sum(1)[:, None] - 2 * q @ p.T + sq[None]
        best = max(best, float(d2.max()))
    return float(np.sqrt(max(best, 0.0)))


# ------------------------------------------------------------------------------------------------ schedule
def radii(schedule: str, d_max: float, steps: int) -> np.ndarray:
    """eps_k for k = 0..steps-1: 0 at k = 0 and d_max at k = steps-1.

    linear: k/(T-1) d_max (the paper's); log: log(1 + k T/(T-1)) / log(T+1) d_max, i.e. the official code's
    log(linspace(1, T+1, T)) scaled to end at d_max (concave: the radius grows fast at first); geometric: log-spaced
    from d_max/100 (convex: most steps use small balls); sqrt: sqrt(k/(T-1)) d_max; sigmoid: a logistic ramp
    centred at T/2."""
    if schedule not in SCHEDULES:
        raise ValueError(f"unknown schedule {schedule!r}")
    s = np.arange(steps, dtype=np.float64) / max(steps - 1, 1)
    if schedule == "linear":
        f = s
    elif schedule == "sqrt":
        f = np.sqrt(s)
    elif schedule == "log":
        f = np.log(np.linspace(1.0, steps + 1.0, steps)) / np.log(steps + 1.0)
    elif schedule == "geometric":
        f = np.exp(np.log(0.01) * (1.0 - s))
    else:
        g = 1 / (1 + np.exp(-12 * (s - 0.5)))
        f = (g - g[0]) / (g[-1] - g[0])
    eps = f * d_max
    eps[0] = 0.0
    return eps


# ------------------------------------------------------------------------------------------------ sampler
class BallSampler:
    """Exact uniform sampling from ball ∩ buffer, vectorized and chunked (see the module docstring).

    ``points`` (K, D) are buffer states in normalized space; ``eps`` (T,) the radius of each diffusion step.
    ``strategy``: ``auto`` (rejection rounds, then KD-tree enumeration of the small balls that remain) or
    ``brute`` (chunked exact enumeration of every query: slower, the reference for tests). ``candidates``: the first
    rejection round's size, ``adaptive`` (from the ball's radius, :meth:`_strategy`) or ``fixed`` (32 for every
    ball, the draws of models before schema 2.8)."""

    def __init__(
        self,
        points: np.ndarray,
        eps: np.ndarray,
        strategy: str = "auto",
        chunk_elems: int = 2_000_000,
        candidates: str = "adaptive",
    ):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.sq = (self.points * self.points).sum(1)
        self.eps = np.asarray(eps, dtype=np.float64)
        if strategy not in ("auto", "brute"):
            raise ValueError(strategy)
        self.strategy = strategy
        if candidates not in ("adaptive", "fixed"):
            raise ValueError(candidates)
        self.candidates = candidates
        # Rejection costs ~1/p tries for a ball holding a fraction p of the buffer; enumeration costs ~p K. They
        # balance near p ~ 1/sqrt(K): try up to ~4 sqrt(K) candidates, then enumerate what is left (small balls).
        self.first_tries = 32
        # balls whose estimated share of the buffer p has p sqrt(K) at least this try rejection first. Half the
        # balance point: queries on the data (where sampling puts them) sit in denser parts of the buffer than the
        # average probe, so balls near the balance hold more points than estimated, and enumerating them means
        # repeated, wider KD-tree queries (on the quickstart's buffer 5x slower at batch 64 than rejection first)
        self.reject_first_at = 0.5
        self.max_tries = int(np.ceil(4 * np.sqrt(self.K)))
        self.chunk_elems = chunk_elems
        self._tree = None
        # squared distances from 256 probe points to (a sample of) the buffer, sorted: the fraction of the buffer
        # within r of a typical buffer point is then one binary search
        prng = np.random.default_rng(0)
        probe = self.points[prng.choice(self.K, size=min(self.K, 256), replace=False)]
        ref = self.points if self.K <= 16384 else self.points[prng.choice(self.K, size=16384, replace=False)]
        d2 = (probe * probe).sum(1)[:, None] - 2 * probe @ ref.T + (ref * ref).sum(1)[None]
        self._probe_d2 = np.sort(d2.ravel())
        # per diffusion step k: how the sampler treats its balls (degrade at one k, as sampling does, looks them up)
        self._level_big, self._level_first = self._strategy(self.eps**2)

    def _strategy(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For balls of squared radii ``r2``: whether to try rejection first (balls expected to hold at least
        ``reject_first_at`` x sqrt(K) points; smaller ones are enumerated directly), and the first round's
        candidates, enough for ~95% of the queries to hit at the ball's estimated share p of the buffer (a handful
        for the large balls, up to ``first_tries`` for the small ones). Both depend on the radius alone, never on
        what is drawn, so the law stays exact."""
        share = self.ball_fraction(np.sqrt(r2))
        big = share * np.sqrt(self.K) >= self.reject_first_at
        with np.errstate(divide="ignore"):
            need = np.ceil(np.log(0.05) / np.log1p(-np.minimum(share, 1 - 1e-9)))
        first = 2 ** np.ceil(np.log2(np.clip(need, 2, self.first_tries))).astype(np.int64)
        if self.candidates == "fixed":
            first = np.full_like(first, self.first_tries)
        return big, first

    def ball_fraction(self, radius):
        """Mean fraction of the buffer inside a ball of ``radius`` around a buffer point (estimated from 256
        probes). Used only to choose between rejection and enumeration, never to decide what is drawn."""
        r = np.asarray(radius, dtype=np.float64)
        return np.searchsorted(self._probe_d2, r * r, side="left") / self._probe_d2.size

    @property
    def K(self) -> int:
        return self.points.shape[0]

    # -------------------------------------------------------------- core
    def sample(self, x: np.ndarray, radius: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """For each query row ``x[q]`` return the index of a buffer point drawn uniformly from
        {j : |points[j] - x[q]| < radius[q]}, or -1 when that set is empty."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        r2 = np.square(np.asarray(radius, dtype=np.float64))
        out = np.full(len(x), -1, dtype=np.int64)
        todo = np.flatnonzero(r2 > 0)
        if self.strategy == "brute":
            if todo.size:
                out[todo] = self._enumerate_brute(x[todo], r2[todo], rng)
            return out
        if self.strategy == "auto":
            levels, inverse = np.unique(r2[todo], return_inverse=True)
            level_big, level_first = self._strategy(levels)
            inverse = inverse.reshape(-1)
            return self._auto(x, r2, todo, level_big[inverse], level_first[inverse], out, rng)
        if todo.size:
            out[todo] = self._enumerate_tree(x[todo], r2[todo], rng)
        return out

    def _auto(self, x, r2, todo, big, first, out, rng) -> np.ndarray:
        """The ``auto`` strategy for the queries ``todo``, told for each whether its ball tries rejection first
        (``big``) and with how many candidates (``first``); fills and returns ``out``."""
        small, rest = todo[~big], []
        if small.size:
            out[small] = self._enumerate_tree(x[small], r2[small], rng)
        if big.any():
            for tries in np.unique(first[big]):
                rest.append(self._reject(x, r2, todo[big & (first == tries)], int(tries), out, rng))
            todo = np.concatenate(rest)
            if todo.size:
                out[todo] = self._enumerate_tree(x[todo], r2[todo], rng)
        return out

    def _reject(self, x, r2, todo: np.ndarray, tries: int, out: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Rejection rounds for the queries ``todo`` (``tries`` candidates each, then 4x more per round, at most
        ``max_tries`` in all); the hits are written into ``out``. Returns the queries still without one."""
        used = 0
        while todo.size and used < self.max_tries:
            tries = min(tries, self.max_tries - used)
            hit_idx = self._rejection_round(x[todo], r2[todo], tries, rng)
            got = hit_idx >= 0
            out[todo[got]] = hit_idx[got]
            todo = todo[~got]
            used += tries
            tries *= 4
        return todo

    def _rejection_round(self, x: np.ndarray, r2: np.ndarray, tries: int, rng: np.random.Generator) -> np.ndarray:
        """``tries`` uniform candidates per query; the first inside the ball, or -1."""
        out = np.full(len(x), -1, dtype=np.int64)
        rows = max(1, self.chunk_elems // (tries * self.points.shape[1]))
        for a in range(0, len(x), rows):
            q, qr2 = x[a : a + rows], r2[a : a + rows]
            cand = rng.integers(0, self.K, size=(len(q), tries))
            diff = self.points[cand] - q[:, None, :]
            inside = np.einsum("qtd,qtd->qt", diff, diff) < qr2[:, None]
            hit = inside.any(axis=1)
            first = inside.argmax(axis=1)
            out[a : a + rows] = np.where(hit, cand[np.arange(len(q)), first], -1)
        return out

    def _enumerate_brute(self, x: np.ndarray, r2: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = np.full(len(x), -1, dtype=np.int64)
        rows = max(1, self.chunk_elems // max(self.K, 1))
        tol = 1e-9
        for a in range(0, len(x), rows):
            q = x[a : a + rows]
            qr2 = r2[a : a + rows, None]
            d2 = (q * q).sum(1)[:, None] - 2.0 * (q @ self.points.T) + self.sq[None]  # (rows, K), float64
            inside = d2 < qr2 - tol
            # the expanded formula may misjudge points within rounding distance of the sphere: recompute those
            # exactly from differences
            near = np.abs(d2 - qr2) <= tol
            if near.any():
                qi, kj = np.nonzero(near)
                dd = self.points[kj] - q[qi]
                inside[qi, kj] = np.einsum("nd,nd->n", dd, dd) < qr2[qi, 0]
            counts = inside.sum(axis=1)
            ok = counts > 0
            pick = np.floor(rng.random(len(q)) * counts).astype(np.int64)  # uniform rank among the inside points
            cums = np.cumsum(inside, axis=1)
            chosen = (cums > pick[:, None]).argmax(axis=1)
            res = np.where(ok, chosen, -1)
            out[a : a + rows] = res
        return out

    def _enumerate_tree(self, x: np.ndarray, r2: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """All buffer points inside each ball via a KD-tree k-nearest query bounded by the radius (vectorized in
        C); a query whose ball may hold more than k points is repeated with 4k."""
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.points)
        out = np.full(len(x), -1, dtype=np.int64)
        expected = 3.0 * self.K / max(self.max_tries, 1)  # balls left after rejection are about this small
        kmax = int(min(self.K, max(16, 2 ** int(np.ceil(np.log2(expected + 1))))))
        todo = np.argsort(r2, kind="stable")  # similar radii together: one distance bound per chunk
        while todo.size:
            q, qr2 = x[todo], r2[todo]
            rows = max(1, self.chunk_elems // kmax)
            saturated = np.zeros(len(q), dtype=bool)
            for a in range(0, len(q), rows):
                sl = slice(a, a + rows)
                own = np.sqrt(qr2[sl]) * (1 + 1e-9) + 1e-12  # a superset of each open ball; filtered exactly below
                dist, idx = self._tree.query(q[sl], k=kmax, distance_upper_bound=float(own.max()))
                dist, idx = np.asarray(dist).reshape(-1, kmax), np.asarray(idx).reshape(-1, kmax)
                # neighbours come sorted by distance: if the k-th is still inside the ball, there may be more
                saturated[sl] = (dist[:, -1] <= own) & (kmax < self.K)
                # inside the ball by the tree's distance, except in a band of rounding width around the sphere,
                # where membership is decided from the differences, as every other path of the sampler does
                r = np.sqrt(qr2[sl])[:, None]
                valid = (idx < self.K) & (dist < r)
                qi, kj = np.nonzero((idx < self.K) & (np.abs(dist - r) <= 1e-9 * (1.0 + r)))
                if qi.size:
                    dd = self.points[idx[qi, kj]] - q[sl][qi]
                    valid[qi, kj] = np.einsum("nd,nd->n", dd, dd) < qr2[sl][qi]
                counts = valid.sum(axis=1)
                pick = np.floor(rng.random(len(counts)) * counts).astype(np.int64)
                chosen = (np.cumsum(valid, axis=1) > pick[:, None]).argmax(axis=1)
                out[todo[sl]] = np.where(counts > 0, idx[np.arange(len(counts)), chosen], -1)
            todo = todo[saturated]  # these balls may hold more than kmax points: enumerate again, wider
            kmax = min(self.K, kmax * 4)
        return out

    # -------------------------------------------------------------- trajectories
    def degrade(self, traj: np.ndarray, k, rng: np.random.Generator, pinned=(0, -1)) -> np.ndarray:
        """D(traj, k): ``traj`` (B, H, D) normalized, ``k`` an int or (B,) ints. Positions in ``pinned`` are left
        unchanged (start and goal); a state whose ball is empty is kept."""
        out = np.array(traj, dtype=np.float64)  # a copy: the pinned states stay as they are
        B, H, D = out.shape
        if tuple(pinned) == (0, -1) and H >= 2:
            free = slice(1, H - 1)  # the usual case: a view, no mask
            n_free = H - 2
        else:
            free = np.ones(H, dtype=bool)
            free[list(pinned)] = False
            n_free = int(free.sum())
        x = out[:, free, :].reshape(-1, D)
        if np.ndim(k) == 0 and self.strategy == "auto":  # one step for every plan (sampling): its strategy is known
            kk = int(k)
            r2 = np.full(len(x), self.eps[kk] ** 2)
            n = len(x)
            idx = np.full(n, -1, dtype=np.int64)
            if self.eps[kk] > 0 and n:
                every = np.arange(n)
                big = np.full(n, bool(self._level_big[kk]))
                self._auto(x, r2, every, big, np.full(n, self._level_first[kk]), idx, rng)
        else:
            k = np.broadcast_to(np.asarray(k, dtype=np.int64), (B,))
            idx = self.sample(x, np.repeat(self.eps[k], n_free), rng)
        hit = idx >= 0
        x[hit] = self.points[idx[hit]]
        out[:, free, :] = x.reshape(B, n_free, D)
        return out

    def random_states(self, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """Buffer states drawn uniformly (the sampling prior): array of ``shape + (D,)``."""
        return self.points[rng.integers(0, self.K, size=shape)]


# ------------------------------------------------------------------------------------------------ on the device
class TorchBallSampler:
    """The same law as :class:`BallSampler` (uniform over the buffer points strictly inside each ball; an empty
    ball keeps the state) computed with torch on the points' device, so training on a GPU never copies a batch to
    the CPU. Membership is decided in float64, like the numpy sampler.

    ``strategy``: ``auto`` (rejection rounds of uniform candidates, then exact enumeration of the queries still
    without a hit) or ``dense`` (enumerate every query: chunked squared distances to all K points, then a uniform
    pick among the inside points as the argmax of i.i.d. uniform keys, i.e. masked Gumbel-max; the reference for
    tests and the dense baseline of the benchmark). On a CPU the numpy sampler is faster: it uses a KD-tree for the
    small balls."""

    def __init__(self, points, eps: np.ndarray, device=None, strategy: str = "auto", chunk_elems: int = 4_000_000):
        import torch

        if strategy not in ("auto", "dense"):
            raise ValueError(strategy)
        self.points = torch.as_tensor(np.asarray(points), dtype=torch.float64, device=device)
        self.sq = (self.points * self.points).sum(1)
        self.eps = torch.as_tensor(np.asarray(eps, dtype=np.float64), device=self.points.device)
        self.strategy = strategy
        self.first_tries = 32
        self.max_tries = int(np.ceil(4 * np.sqrt(self.K)))
        self.chunk_elems = chunk_elems

    @property
    def K(self) -> int:
        return self.points.shape[0]

    @property
    def device(self):
        return self.points.device

    def generator(self, rng: np.random.Generator):
        """A torch generator on the sampler's device, seeded from ``rng`` (one draw): determinism follows the
        caller's numpy stream."""
        import torch

        g = torch.Generator(device=self.device)
        g.manual_seed(int(rng.integers(0, 2**63 - 1)))
        return g

    def sample(self, x, radius, gen):
        """Index of a buffer point drawn uniformly from {j : |points[j] - x[q]| < radius[q]} per query row, or -1
        when that set is empty. ``x`` (N, D) and ``radius`` (N,) tensors (any float dtype), ``gen`` a generator on
        the sampler's device."""
        import torch

        x = x.to(device=self.device, dtype=torch.float64)
        r2 = torch.as_tensor(radius, device=self.device, dtype=torch.float64) ** 2
        out = torch.full((x.shape[0],), -1, dtype=torch.long, device=self.device)
        todo = torch.nonzero(r2 > 0).flatten()
        if self.strategy == "auto":
            tries, used = self.first_tries, 0
            while todo.numel() and used < self.max_tries:
                tries = min(tries, self.max_tries - used)
                hit = self._rejection_round(x[todo], r2[todo], tries, gen)
                got = hit >= 0
                out[todo[got]] = hit[got]
                todo = todo[~got]
                used += tries
                tries *= 4
        if todo.numel():
            out[todo] = self._enumerate(x[todo], r2[todo], gen)
        return out

    def _rejection_round(self, x, r2, tries: int, gen):
        import torch

        out = torch.full((x.shape[0],), -1, dtype=torch.long, device=self.device)
        rows = max(1, self.chunk_elems // (tries * self.points.shape[1]))
        for a in range(0, x.shape[0], rows):
            q, qr2 = x[a : a + rows], r2[a : a + rows]
            cand = torch.randint(0, self.K, (q.shape[0], tries), generator=gen, device=self.device)
            diff = self.points[cand] - q[:, None, :]
            inside = (diff * diff).sum(-1) < qr2[:, None]
            first = inside.to(torch.uint8).argmax(dim=1)  # the first candidate inside (0 when none is)
            picked = cand.gather(1, first[:, None]).squeeze(1)
            out[a : a + rows] = torch.where(inside.any(dim=1), picked, -1)
        return out

    def _enumerate(self, x, r2, gen):
        import torch

        out = torch.full((x.shape[0],), -1, dtype=torch.long, device=self.device)
        rows = max(1, self.chunk_elems // max(self.K, 1))
        tol = 1e-9
        for a in range(0, x.shape[0], rows):
            q, qr2 = x[a : a + rows], r2[a : a + rows, None]
            d2 = (q * q).sum(1)[:, None] - 2.0 * (q @ self.points.T) + self.sq[None]
            inside = d2 < qr2 - tol
            near = (d2 - qr2).abs() <= tol  # within rounding of the sphere: decide from exact differences
            if bool(near.any()):
                qi, kj = torch.nonzero(near, as_tuple=True)
                dd = self.points[kj] - q[qi]
                inside[qi, kj] = (dd * dd).sum(1) < qr2[qi, 0]
            keys = torch.rand(inside.shape, generator=gen, device=self.device, dtype=torch.float32)
            keys = torch.where(inside, keys, -1.0)
            best = keys.argmax(dim=1)  # the argmax of i.i.d. uniform keys over the inside points: uniform among them
            out[a : a + rows] = torch.where(inside.any(dim=1), best, -1)
        return out

    def degrade(self, traj, k, gen, pinned=(0, -1)):
        """D(traj, k) for a (B, H, D) tensor on any device; ``k`` an int or (B,) ints; ``pinned`` positions kept,
        as :meth:`BallSampler.degrade`. Returns a tensor of ``traj``'s dtype and device."""
        import torch

        B, H, D = traj.shape
        t = traj.to(self.device)
        k = torch.as_tensor(np.broadcast_to(np.asarray(k, dtype=np.int64), (B,)).copy(), device=self.device)
        free = torch.ones(H, dtype=torch.bool, device=self.device)
        free[list(pinned)] = False
        x = t[:, free, :].reshape(-1, D)
        idx = self.sample(x, self.eps[k].repeat_interleave(int(free.sum())), gen)
        y = torch.where((idx >= 0)[:, None], self.points[idx.clamp(min=0)].to(t.dtype), x)
        out = t.clone()
        out[:, free, :] = y.reshape(B, -1, D)
        return out.to(traj.device)

    def degrade_given(self, traj, radius: float, u, free: slice):
        """D(traj, k) at one radius with its randomness given, for a CUDA graph: static shapes, no host
        synchronisation. ``traj`` (B, H, D); ``free``: the positions degraded; ``u`` (B, n_free) uniforms in
        [0, 1): each state takes the point of rank floor(u * n) among the n buffer points strictly inside its ball
        (in index order), so the draw is uniform over them; an empty ball keeps the state. One pass over all
        (query, point) pairs in float64: for the batch sizes a graph serves."""
        import torch

        B, H, D = traj.shape
        q = traj[:, free, :].reshape(-1, D).to(torch.float64)
        d2 = torch.zeros((q.shape[0], self.K), dtype=torch.float64, device=self.device)
        for d in range(D):  # squared differences, summed dimension by dimension (no cancellation near the sphere)
            d2.add_((q[:, d, None] - self.points[None, :, d]).square_())
        inside = d2 < float(radius) ** 2
        count = inside.sum(dim=1)
        rank = torch.minimum((u.reshape(-1).to(torch.float64) * count).long(), (count - 1).clamp(min=0))
        first = (inside.cumsum(dim=1, dtype=torch.int32) > rank[:, None].to(torch.int32)).to(torch.uint8).argmax(dim=1)
        y = torch.where((count > 0)[:, None], self.points[first], q).to(traj.dtype)
        out = traj.clone()
        out[:, free, :] = y.reshape(B, -1, D)
        return out

    def random_states(self, shape: tuple[int, ...], gen):
        """Buffer states drawn uniformly (the sampling prior): a float64 tensor of ``shape + (D,)``."""
        import torch

        return self.points[torch.randint(0, self.K, shape, generator=gen, device=self.device)]
