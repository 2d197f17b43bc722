"""Replay-buffer balls measured along the demonstrations: the buffer's transition graph and exact uniform sampling
from geodesic balls.

CDRB's ball D(s, eps) is Euclidean in the normalised features, so near a thin wall it holds buffer states from both
sides, and a degradation may swap a state across the wall. The demonstrations say which buffer states are
neighbours in free space: consecutive states of one demonstration. So:

* :func:`transition_graph`: each demonstration state is mapped to its buffer state (the nearest buffer point, the
  cluster it belongs to: in every feature, or in the position dims alone with ``cdrb cluster --graph-join
  position``); consecutive distinct buffer states of one demonstration are joined by an undirected edge weighted by
  their Euclidean distance in the normalised features. No map is read: the data alone say what is free.
* :class:`GeodesicBalls`: a query state is attached to the graph at its nearest buffer state ``a`` (the step costs
  the Euclidean distance to it), and its ball of radius eps holds the buffer states ``j`` with
  ``|x - p_a| + g(a, j) < eps``, ``g`` the shortest-path distance along the graph. A draw is uniform over that set,
  exactly: every node's shortest-path distances to all others are computed once and sorted, so a ball is a prefix
  of its anchor's sorted list and a uniform rank in it is one binary search. States of another connected component
  are never in a ball (their distance is infinite); a query farther from its anchor than eps has an empty ball (the
  state is kept, as for an empty Euclidean ball).

The radii: the paper's schedule grows eps_k to the buffer's Euclidean diameter. Stretched to the graph's diameter
(``method.geodesic_radii = "scaled"``), it gives far larger balls at every step, since paths along a
demonstration zig-zag through the features (on a Fetch buffer the graph's diameter is ~11x the Euclidean one and
its first ball holds about a fifth of the buffer against the paper's 0.3%): a degradation much stronger than the
paper's from the first step on. :meth:`GeodesicBalls.matched_radii` (the default, ``"matched"``) gives each step
the least graph radius, not below the paper's, that holds as many (centre, member) pairs of buffer states as the
paper's Euclidean radius of that step holds among pairs of one component, so each step degrades as strongly as the
paper's and only which states a ball holds differs; the last radius stays d_max (the graph's diameter).

Memory is K^2 (a float64 distance and an int32 index per pair: 11 MiB at K = 1,000, 1.1 GiB at K = 10,000, whose
all-pairs shortest paths take about 35 s on one core; `benchmarks/geodesic_balls.py` measures both).
"""

from __future__ import annotations

import numpy as np

from cdrb_cli.buffer import BallSampler

#: the largest buffer the all-pairs tables are built for (12 bytes a pair: about 1.6 GiB at this size)
MAX_NODES = 12_000


def nearest_point(points: np.ndarray, states: np.ndarray) -> np.ndarray:
    """Index of the nearest of ``points`` (K, D) to each of ``states`` (N, D) (ties: the lowest index)."""
    from scipy.spatial import cKDTree

    return cKDTree(np.asarray(points, dtype=np.float64)).query(np.asarray(states, dtype=np.float64))[1].astype(np.int64)


def transition_graph(
    points: np.ndarray, states: np.ndarray, episode: np.ndarray, dims: list[int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The buffer's transition graph: ``states`` (N, D) are the demonstrations' states in the buffer's normalised
    features, in order, ``episode`` (N,) the demonstration each belongs to (consecutive rows of one demonstration
    are consecutive states); each state joins the graph at its nearest buffer point in the feature columns ``dims``
    (all of them by default). Returns (edges (E, 2) int64 with i < j, each pair once, sorted; weights (E,) float64,
    the Euclidean distance between the two buffer points in every feature). Deterministic: no randomness enters."""
    points = np.asarray(points, dtype=np.float64)
    cols = slice(None) if dims is None else list(dims)
    node = nearest_point(points[:, cols], np.asarray(states, dtype=np.float64)[:, cols])
    episode = np.asarray(episode)
    same = (episode[1:] == episode[:-1]) & (node[1:] != node[:-1])
    a, b = node[:-1][same], node[1:][same]
    pairs = np.unique(np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1), axis=0)
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.float64)
    weights = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    return pairs.astype(np.int64), weights


def graph_summary(n_nodes: int, edges: np.ndarray) -> dict:
    """Size, connected components and degrees of a transition graph (what `cdrb inspect` shows)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_nodes, n_nodes))
    n_comp, labels = connected_components(adj, directed=False)
    degree = np.bincount(e.ravel(), minlength=n_nodes)
    sizes = np.bincount(labels)
    return {
        "nodes": int(n_nodes),
        "edges": int(len(e)),
        "components": int(n_comp),
        "largest_component": int(sizes.max()) if sizes.size else 0,
        "isolated_nodes": int((degree == 0).sum()),
        "mean_degree": round(float(degree.mean()), 3) if n_nodes else 0.0,
        "max_degree": int(degree.max()) if n_nodes else 0,
    }


def graph_diameter(n_nodes: int, edges: np.ndarray, weights: np.ndarray) -> float | None:
    """The largest finite shortest-path distance between two of ``n_nodes`` points along the graph: the radius a
    geodesic ball needs to hold a whole component from anywhere in it (None above :data:`MAX_NODES` points)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    if n_nodes > MAX_NODES:
        return None
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.asarray(weights, np.float64), (e[:, 0], e[:, 1])), shape=(n_nodes, n_nodes)).tocsr()
    dist = dijkstra(graph, directed=False)
    finite = dist[np.isfinite(dist)]
    return float(finite.max()) if finite.size else 0.0


class GeodesicBalls:
    """Exact uniform sampling from geodesic balls of a buffer's transition graph (see the module docstring); the
    same ``sample(x, radius, rng)`` as :class:`~cdrb_cli.buffer.BallSampler`."""

    def __init__(self, points: np.ndarray, edges: np.ndarray, weights: np.ndarray, eps: np.ndarray | None = None):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.eps = None if eps is None else np.asarray(eps, dtype=np.float64)  # the radius of each diffusion step
        self.edges, self.weights = np.asarray(edges, dtype=np.int64).reshape(-1, 2), np.asarray(weights, np.float64)
        k = len(self.points)
        if k > MAX_NODES:
            raise ValueError(f"geodesic balls need K <= {MAX_NODES} buffer points (all-pairs tables), got {k}")
        e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        w = np.asarray(weights, dtype=np.float64)
        graph = coo_matrix((w, (e[:, 0], e[:, 1])), shape=(k, k)).tocsr()
        dist = dijkstra(graph, directed=False)  # (K, K), inf between components
        self.order = np.argsort(dist, axis=1, kind="stable").astype(np.int32)
        self.sorted = np.take_along_axis(dist, self.order.astype(np.int64), axis=1)
        self._tree = None

    @property
    def K(self) -> int:
        return self.points.shape[0]

    def anchor(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each query's nearest buffer point and its Euclidean distance to it."""
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.points)
        d, a = self._tree.query(np.asarray(x, dtype=np.float64))
        return np.asarray(a, dtype=np.int64), np.asarray(d, dtype=np.float64)

    def _below(self, rows: np.ndarray, left: np.ndarray) -> np.ndarray:
        """For each anchor ``rows[q]`` the number of buffer points whose graph distance to it is below ``left[q]``:
        one binary search per row of the sorted table, all rows a step at a time (log2(K) gathers)."""
        lo, hi = np.zeros(len(rows), dtype=np.int64), np.full(len(rows), self.K, dtype=np.int64)
        for _ in range(int(self.K).bit_length()):
            mid = (lo + hi) // 2
            below = self.sorted[rows, np.minimum(mid, self.K - 1)] < left
            open_ = lo < hi
            lo = np.where(open_ & below, mid + 1, lo)
            hi = np.where(open_ & ~below, mid, hi)
        return lo

    def pairs_below(self, radius: float) -> int:
        """The number of ordered pairs (i, j) of buffer points (i = j included) with graph distance below
        ``radius``: how many members the balls of that radius around every buffer point hold together."""
        rows = np.arange(self.K)
        return int(self._below(rows, np.full(self.K, float(radius))).sum())

    def matched_radii(self, shape: np.ndarray, last: float) -> np.ndarray:
        """Graph radii matched to a Euclidean schedule: ``shape`` is the schedule's radii for a diameter of 1
        (``radii(schedule, 1.0, T)``), scaled here by the buffer's Euclidean diameter as the paper's balls are.
        Step k's radius is the least r >= eps_k (the Euclidean radius: a geodesic ball is never wider than the
        Euclidean one of its radius, so below it a query off the buffer would find an empty ball where the paper's
        finds its neighbour) whose balls around the K buffer points hold at least as many members together
        (:meth:`pairs_below`) as that step's Euclidean balls hold among pairs of one connected component (a ball
        never reaches another), counted exactly. The last radius is ``last`` (d_max: by default the graph's
        diameter, so the last ball holds each component); radii above ``last`` (a d_max set smaller) are cut to it.
        Deterministic: distances from ``scipy.spatial.distance.cdist`` (no BLAS, so no dependence on threads),
        shortest paths, a bisection; about 0.3 s at K = 1,000 and T = 16, growing with K log K and T."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial.distance import cdist

        graph = coo_matrix((np.ones(len(self.edges)), (self.edges[:, 0], self.edges[:, 1])), shape=(self.K, self.K))
        _, label = connected_components(graph, directed=False)
        chunk = max(1, 4_000_000 // self.K)
        rows = [slice(a, a + chunk) for a in range(0, self.K, chunk)]
        reference = np.asarray(shape, dtype=np.float64) * max(cdist(self.points[r], self.points).max() for r in rows)
        counts = np.zeros(len(reference) + 1, dtype=np.int64)
        for r in rows:
            d = cdist(self.points[r], self.points)
            d = d[label[r][:, None] == label[None]]  # pairs of one component
            counts += np.bincount(np.searchsorted(reference, d, side="right"), minlength=len(counts))
        wanted = np.cumsum(counts)[: len(reference)]  # d < eps_k exactly when k >= the number of radii <= d
        anchors = np.arange(self.K)
        finite = self._below(anchors, np.full(self.K, np.inf))  # each row's finite entries come first
        top = float(np.nextafter(self.sorted[anchors, finite - 1].max(), np.inf))
        out = np.zeros(len(reference), dtype=np.float64)
        for k in range(1, len(reference) - 1):
            lo, hi = float(reference[k]), top
            if self.pairs_below(lo) >= wanted[k] or lo >= hi:
                out[k] = lo
                continue
            while True:  # pairs_below(lo) < wanted <= pairs_below(hi)
                mid = lo + (hi - lo) / 2
                if mid <= lo or mid >= hi:
                    break
                lo, hi = (lo, mid) if self.pairs_below(mid) >= wanted[k] else (mid, hi)
            out[k] = hi
        if len(out) > 1:
            out[-1] = last
        return np.minimum(out, last)

    def ball_sizes(self, x: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(anchor, number of buffer points in each query's geodesic ball)."""
        a, d = self.anchor(x)
        left = np.asarray(radius, dtype=np.float64) - d  # what the graph may still spend
        # the entries of the anchor's sorted row below ``left`` (strictly inside), so a call costs log2(K) gathers
        # instead of reading K distances per query
        return a, self._below(a, left)

    def members(self, x: np.ndarray, radius: float) -> np.ndarray:
        """The buffer indices in the geodesic ball of radius ``radius`` around one query ``x`` (for tests)."""
        a, n = self.ball_sizes(np.asarray(x, dtype=np.float64)[None], np.array([radius]))
        return np.sort(self.order[a[0], : n[0]].astype(np.int64))

    def sample(self, x: np.ndarray, radius: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """For each query row ``x[q]`` the index of a buffer point drawn uniformly from its geodesic ball of radius
        ``radius[q]``, or -1 when that ball is empty."""
        x = np.asarray(x, dtype=np.float64)
        radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(x),))
        a, n = self.ball_sizes(x, radius)
        u = rng.random(len(x))
        rank = np.minimum((u * n).astype(np.int64), np.maximum(n - 1, 0))
        out = self.order[a, rank].astype(np.int64)
        return np.where(n > 0, out, -1)

    # D(traj, k) and the sampling prior are the Euclidean sampler's own code over this class's ``sample``: the
    # pinned positions left alone, a state whose ball is empty kept, buffer states drawn uniformly
    strategy = "geodesic"
    degrade = BallSampler.degrade
    random_states = BallSampler.random_states

    def subset(self, keep: np.ndarray) -> GeodesicBalls:
        """The balls of the buffer states ``keep`` (a boolean mask) marks: a removed state takes its edges with it,
        so a path that led through it is gone (a new obstacle cuts the graph, no map test in the sampler)."""
        keep = np.asarray(keep, dtype=bool)
        new = np.full(self.K, -1, dtype=np.int64)
        new[keep] = np.arange(int(keep.sum()))
        both = keep[self.edges[:, 0]] & keep[self.edges[:, 1]] if len(self.edges) else np.zeros(0, bool)
        return GeodesicBalls(self.points[keep], new[self.edges[both]], self.weights[both], self.eps)
