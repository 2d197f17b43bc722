"""Routes through the replay buffer, for planning around obstacles the training data never saw.

The buffer's states are where the robot has been. A graph joins each buffer state to its nearest neighbours (in
the obstacle dimensions) by a straight step that touches no obstacle of the scene planned in; a start and a goal
join it the same way. The shortest route from start to goal through that graph, resampled to a plan's length at
even spacing, is a plan made only of visited states and free steps. `--route-k K` starts the planner's own repair
from it (CDRB: degraded to step K by the ball sampler and restored; a Gaussian planner: noised to timestep K and
denoised), so the model turns the route into a plan of its kind instead of sampling one from scratch that follows
the data's habits through a passage that is now closed.
"""

from __future__ import annotations

import numpy as np

from cdrb_cli.envs.registry import family_of
from cdrb_cli.envs.spec import EnvSpec

#: neighbours each buffer state (and each start and goal) is joined to, when the step between them is free
NEIGHBOURS = 16
#: with a clearance, a step to or from a buffer state that close to an obstacle costs this many times its length
NEAR_COST = 5.0


class BufferGraph:
    """The graph of ``states`` (K, F) raw feature rows (the state first) joined by free straight steps.

    ``clearance`` (in the obstacle dimensions' units): a buffer state that collides when moved that far along any
    obstacle dimension (either way) is *near* an obstacle, and a step to or from it costs :data:`NEAR_COST` times its
    length, so the shortest route keeps that clearance wherever the buffer allows (the scripted experts keep one; a
    route that hugs a wall's end leads the body into it). 0: every free step costs its length."""

    def __init__(self, spec: EnvSpec, states: np.ndarray, neighbours: int = NEIGHBOURS, clearance: float = 0.0):
        from scipy.spatial import cKDTree

        self.spec = spec
        self.family = family_of(spec)
        self.states = np.asarray(states, dtype=np.float64)
        self.dims = list(spec.obstacles.dims)
        self.near = self._near(clearance)
        self.k = int(min(neighbours, max(len(self.states) - 1, 1)))
        self.tree = cKDTree(self.states[:, self.dims])
        K = len(self.states)
        dist, nbr = self.tree.query(self.states[:, self.dims], k=self.k + 1)
        i = np.repeat(np.arange(K), self.k + 1)
        j, d = nbr.reshape(-1), dist.reshape(-1)
        keep = (j != i) & (j < K)
        i, j, d = i[keep], j[keep], d[keep]
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        _, first = np.unique(lo * K + hi, return_index=True)  # each undirected pair once
        i, j, d = lo[first], hi[first], d[first]
        free = ~self._crosses(self.states[i], self.states[j])
        i, j, d = i[free], j[free], np.maximum(d[free], 1e-9)
        d = d * np.where(self.near[i] | self.near[j], NEAR_COST, 1.0)
        self.edges = (np.concatenate([i, j]), np.concatenate([j, i]), np.concatenate([d, d]))
        self.n_edges = int(free.sum())

    def _near(self, clearance: float) -> np.ndarray:
        """Per buffer state: does it collide when moved ``clearance`` along some obstacle dimension?"""
        near = np.zeros(len(self.states), dtype=bool)
        if clearance <= 0:
            return near
        obs = self.spec.obs_dim
        for dim in self.dims:
            for sign in (-1.0, 1.0):
                moved = self.states[:, :obs].copy()
                moved[:, dim] += sign * clearance
                near |= np.asarray(self.family.in_collision(self.spec, moved), dtype=bool)
        return near

    def _crosses(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Whether the straight step between raw states a and b (n, F) touches an obstacle."""
        obs = self.spec.obs_dim
        return np.asarray(self.family.path_in_collision(self.spec, np.stack([a[:, :obs], b[:, :obs]], 1)), bool)

    def _attach(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The buffer states a raw state joins by a free step among its nearest, and their distances."""
        d, j = self.tree.query(state[self.dims], k=self.k)
        d, j = np.atleast_1d(d), np.atleast_1d(j)
        ok = j < len(self.states)
        d, j = d[ok], j[ok]
        free = ~self._crosses(np.repeat(state[None], len(j), 0), self.states[j])
        j, d = j[free], np.maximum(d[free], 1e-9)
        return j, d * np.where(self.near[j], NEAR_COST, 1.0)

    def route(self, start: np.ndarray, goal: np.ndarray, horizon: int) -> np.ndarray | None:
        """The shortest route from ``start`` to ``goal`` (raw feature rows) through the graph, as ``horizon`` raw
        feature rows at even spacing along it (start and goal exact); None when no route joins them."""
        points = self.polyline(start, goal)
        return None if points is None else resample_evenly(points, self.dims, horizon)

    def waypoint(self, start: np.ndarray, goal: np.ndarray, reach: float) -> np.ndarray | None:
        """The point ``reach`` along the shortest route from ``start`` to ``goal`` (raw feature rows; arc length
        in the obstacle dimensions), between two route points joined by a free step; ``goal`` itself when the route
        is no longer than ``reach``; None when no route joins them."""
        return _along(self.polyline(start, goal), self.dims, reach, goal)

    def polyline(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """The shortest route from ``start`` to ``goal`` through the graph as its points (m, F): the start, the
        buffer states it passes, the goal; the two alone when the straight step between them is free; None when no
        route joins them."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        start, goal = np.asarray(start, np.float64), np.asarray(goal, np.float64)
        if not self._crosses(start[None], goal[None])[0]:
            return np.stack([start, goal])
        s_nodes, s_d = self._attach(start)
        g_nodes, g_d = self._attach(goal)
        if not len(s_nodes) or not len(g_nodes):
            return None
        K = len(self.states)
        S, G = K, K + 1  # the start and the goal as two extra nodes
        rows = np.concatenate([self.edges[0], np.full(len(s_nodes), S), g_nodes])
        cols = np.concatenate([self.edges[1], s_nodes, np.full(len(g_nodes), G)])
        vals = np.concatenate([self.edges[2], s_d, g_d])
        graph = coo_matrix((vals, (rows, cols)), shape=(K + 2, K + 2)).tocsr()
        dist, pred = dijkstra(graph, directed=True, indices=S, return_predecessors=True)
        if not np.isfinite(dist[G]):
            return None
        path, node = [], pred[G]
        while node != S:
            path.append(int(node))
            node = pred[node]
        return np.concatenate([start[None], self.states[path[::-1]], goal[None]])


class TransitionRoutes:
    """Routes along the buffer's transition graph (:func:`~cdrb_cli.geodesic.transition_graph`: buffer states that
    one demonstration visited one after the other are joined), so no map is read: the data alone say where the robot
    can go. A start or goal joins the graph at its nearest buffer state (in the obstacle dimensions); a step's
    length is measured in those dimensions. The same :meth:`polyline` / :meth:`waypoint` as :class:`BufferGraph`.

    ``states`` (K, F) raw feature rows, ``edges`` (E, 2) indices into them."""

    def __init__(self, spec: EnvSpec, states: np.ndarray, edges: np.ndarray):
        from scipy.sparse import coo_matrix
        from scipy.spatial import cKDTree

        self.states = np.asarray(states, dtype=np.float64)
        self.dims = list(spec.obstacles.dims)
        K = len(self.states)
        e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        length = np.maximum(
            np.linalg.norm(self.states[e[:, 0]][:, self.dims] - self.states[e[:, 1]][:, self.dims], axis=1), 1e-9
        )
        rows, cols = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])
        self.graph = coo_matrix((np.concatenate([length, length]), (rows, cols)), shape=(K, K)).tocsr()
        self.tree = cKDTree(self.states[:, self.dims])
        self._toward: dict[int, np.ndarray] = {}  # goal node -> each node's next node toward it (-9999: none)

    def polyline(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """The route from ``start`` to ``goal`` (raw feature rows): the start, the buffer states of the shortest
        path between their nearest buffer states, the goal; None when the graph joins no path between them."""
        from scipy.sparse.csgraph import dijkstra

        start, goal = np.asarray(start, np.float64), np.asarray(goal, np.float64)
        a = int(self.tree.query(start[self.dims])[1])
        b = int(self.tree.query(goal[self.dims])[1])
        if b not in self._toward:  # one search per goal: every re-plan toward it walks the same tree
            self._toward[b] = dijkstra(self.graph, directed=False, indices=b, return_predecessors=True)[1]
        nxt = self._toward[b]
        path, node = [a], a
        while node != b:
            node = int(nxt[node])
            if node < 0:
                return None
            path.append(node)
        return np.concatenate([start[None], self.states[path], goal[None]])

    def waypoint(self, start: np.ndarray, goal: np.ndarray, reach: float) -> np.ndarray | None:
        """As :meth:`BufferGraph.waypoint`, along the transition graph."""
        return _along(self.polyline(start, goal), self.dims, reach, goal)


def _along(points: np.ndarray | None, dims: list[int], reach: float, goal: np.ndarray) -> np.ndarray | None:
    """The point ``reach`` along the polyline ``points`` (arc length over ``dims``), ``goal`` itself when the polyline
    is no longer; None for no polyline."""
    if points is None:
        return None
    seg = np.linalg.norm(np.diff(points[:, dims], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= reach:
        return np.asarray(goal, np.float64).copy()
    i = int(np.searchsorted(s, reach, side="right")) - 1  # the segment that holds arc length ``reach``
    w = (reach - s[i]) / max(seg[i], 1e-12)
    return (1 - w) * points[i] + w * points[i + 1]


def resample_evenly(points: np.ndarray, dims: list[int], n: int) -> np.ndarray:
    """``n`` rows evenly spaced by arc length (over ``dims``) along the polyline ``points`` (m, F), every feature
    interpolated linearly; the first and last rows are the polyline's ends."""
    seg = np.linalg.norm(np.diff(points[:, dims], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(points[:1], n, axis=0)
    t = np.linspace(0.0, s[-1], n)
    out = np.stack([np.interp(t, s, points[:, f]) for f in range(points.shape[1])], axis=1)
    out[0], out[-1] = points[0], points[-1]
    return out


def waypoint_points(graph: BufferGraph | TransitionRoutes, reach: float, features: int):
    """A function of raw states (n, obs_dim) and goal states (n, obs_dim) that gives each pair's point ``reach``
    along its shortest route through ``graph`` (a raw feature row; the goal itself when the route is that short),
    or None where no route joins them."""

    def points(states: np.ndarray, goal_states: np.ndarray) -> list[np.ndarray | None]:
        out = []
        for s, g in zip(states, goal_states):
            pad = np.zeros(features - len(s))
            out.append(graph.waypoint(np.concatenate([s, pad]), np.concatenate([g, pad]), reach))
        return out

    return points


def waypoint_aims(graph: BufferGraph | TransitionRoutes, spec: EnvSpec, reach: float, features: int):
    """The aims of plans toward far goals: a function of raw states (n, obs_dim) and goal states (n, obs_dim) that
    gives each pair's waypoint ``reach`` along its shortest route through ``graph`` as a goal state (the goal
    itself when the route is that short, or when no route joins them)."""
    family = family_of(spec)
    dims = list(spec.goal_dims)
    points = waypoint_points(graph, reach, features)

    def aims(states: np.ndarray, goal_states: np.ndarray) -> np.ndarray:
        out = np.array(goal_states, dtype=np.float64)
        for i, point in enumerate(points(states, goal_states)):
            if point is not None:
                out[i] = family.goal_state(spec, point[None, dims])[0]
        return out

    return aims


def waypoint_goals(graph: BufferGraph | TransitionRoutes, spec: EnvSpec, reach: float):
    """The goals a closed-loop policy is given toward far goals: a function of raw states (n, obs_dim) and the
    episodes' goals (n, goal_dim) that gives each one's waypoint ``reach`` along its shortest route through
    ``graph`` as a goal (the goal itself when the route is that short, or when no route joins them)."""
    family = family_of(spec)
    dims = list(spec.goal_dims)
    points = waypoint_points(graph, reach, spec.obs_dim)

    def goals_of(states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        out = np.array(goals, dtype=np.float64)
        for i, point in enumerate(points(states, family.goal_state(spec, out))):
            if point is not None:
                out[i] = point[dims]
        return out

    return goals_of
