"""Generic obstacle geometry: axis-aligned boxes over some state dimensions, distances to them, and the collision
test (vectorized over any batch of states). :class:`BoxObstacles` is the obstacle record an EnvSpec holds; this
module imports no other part of ``envs``, so the spec, the registry and the families can all use it."""

from __future__ import annotations

import numpy as np
from pydantic import Field, model_validator

from cdrb_cli.schema_base import Record

MAX_BOXES = 20_000


class BoxObstacles(Record):
    """Axis-aligned boxes over the state dimensions ``dims``. A state collides when the point made of those
    dimensions is closer than ``inflate`` to any box (the agent's own radius), or lies outside ``[low, high]``."""

    dims: list[int] = Field(min_length=1, max_length=16)
    centers: list[list[float]] = Field(max_length=MAX_BOXES)
    half_sizes: list[list[float]] = Field(max_length=MAX_BOXES)
    inflate: float = Field(0.0, ge=0)
    low: list[float]
    high: list[float]

    @model_validator(mode="after")
    def _check_shapes(self) -> BoxObstacles:
        d = len(self.dims)
        if len(self.centers) != len(self.half_sizes):
            raise ValueError("centers and half_sizes must have the same length")
        if any(len(c) != d for c in self.centers) or any(len(h) != d for h in self.half_sizes):
            raise ValueError("every box needs one center and half size per dimension in dims")
        if len(self.low) != d or len(self.high) != d or any(lo >= hi for lo, hi in zip(self.low, self.high)):
            raise ValueError("low/high must give one increasing bound per dimension")
        if any(h < 0 for hs in self.half_sizes for h in hs):
            raise ValueError("half sizes must be non-negative")
        return self


def box_distance(points: np.ndarray, centers: np.ndarray, half_sizes: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Euclidean distance from each point (..., d) to the nearest box (0 inside a box). Vectorized, chunked."""
    pts = np.asarray(points, dtype=np.float64)
    flat = pts.reshape(-1, pts.shape[-1])
    out = np.empty(flat.shape[0], dtype=np.float64)
    if centers.shape[0] == 0:
        out[:] = np.inf
        return out.reshape(pts.shape[:-1])
    for a in range(0, flat.shape[0], chunk):
        p = flat[a : a + chunk]
        gap = np.abs(p[:, None, :] - centers[None]) - half_sizes[None]  # (n, M, d)
        d = np.sqrt(np.square(np.maximum(gap, 0.0)).sum(-1))
        out[a : a + chunk] = d.min(axis=1)
    return out.reshape(pts.shape[:-1])


def box_arrays(obstacles: BoxObstacles) -> tuple[np.ndarray, np.ndarray]:
    """(centers (M, d), half_sizes (M, d)) as arrays."""
    d = len(obstacles.dims)
    centers = np.asarray(obstacles.centers, dtype=np.float64).reshape(-1, d)
    halves = np.asarray(obstacles.half_sizes, dtype=np.float64).reshape(-1, d)
    return centers, halves


def _touches(distance: np.ndarray, inflate: float) -> np.ndarray:
    """Closer than the agent's radius; for a point agent (radius 0), inside or on a box."""
    return distance < inflate if inflate > 0 else distance <= 0.0


def in_boxes(states: np.ndarray, obstacles: BoxObstacles) -> np.ndarray:
    """Boolean mask over states (..., D): True where the agent (a ball of radius ``obstacles.inflate`` centred at
    the state's obstacle dimensions) overlaps a box, or its centre lies outside ``[low, high]`` or is not a finite
    point (a NaN compares false with every bound, and would otherwise pass as free)."""
    states = np.asarray(states)
    pts = states[..., obstacles.dims].astype(np.float64)
    centers, halves = box_arrays(obstacles)
    hit = _touches(box_distance(pts, centers, halves), obstacles.inflate)
    low, high = np.asarray(obstacles.low), np.asarray(obstacles.high)
    outside = np.any((pts < low) | (pts > high) | ~np.isfinite(pts), axis=-1)
    return hit | outside


def segment_box_distance(
    a: np.ndarray,
    b: np.ndarray,
    centers: np.ndarray,
    half_sizes: np.ndarray,
    within: float | None = None,
    iters: int = 48,
    chunk: int = 8192,
) -> np.ndarray:
    """Smallest Euclidean distance from each segment [a, b] (..., d) to the nearest box (0 where it touches one).

    The distance from a + t (b - a) to a convex box is convex in t, so a ternary search on t in [0, 1] finds its
    minimum (``iters`` = 48 shrinks the interval by (2/3)^48 ~ 4e-9 of the segment); the endpoints are included.
    Distance is 1-Lipschitz, so no point of a segment of length L is closer than min(end distances) - L/2: with
    ``within`` set, pairs whose bound is already >= ``within`` skip the search (their value is then only known to be
    >= ``within``), which makes the usual case (short steps far from walls) cheap."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    shape = a.shape[:-1]
    fa, fb = a.reshape(-1, a.shape[-1]), b.reshape(-1, b.shape[-1])
    out = np.empty(fa.shape[0], dtype=np.float64)
    if centers.shape[0] == 0:
        out[:] = np.inf
        return out.reshape(shape)

    def dist(p, c, h):
        return np.sqrt(np.square(np.maximum(np.abs(p - c) - h, 0.0)).sum(-1))

    # a state that is no point (NaN, inf) gives NaN here; in_boxes counts it as a collision
    with np.errstate(invalid="ignore"):
        for s in range(0, fa.shape[0], chunk):
            p0, d = fa[s : s + chunk, None, :], (fb - fa)[s : s + chunk, None, :]
            best = np.minimum(dist(p0, centers[None], half_sizes[None]), dist(p0 + d, centers[None], half_sizes[None]))
            need = best > 0
            if within is not None:
                need &= best - np.linalg.norm(d, axis=-1) / 2 < within
            i, j = np.nonzero(need)
            if i.size:
                p, dd, c, h = p0[i, 0], d[i, 0], centers[j], half_sizes[j]
                lo, hi = np.zeros(i.size), np.ones(i.size)
                for _ in range(iters):
                    m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
                    left = dist(p + m1[:, None] * dd, c, h) <= dist(p + m2[:, None] * dd, c, h)
                    hi = np.where(left, m2, hi)
                    lo = np.where(left, lo, m1)
                mid = dist(p + ((lo + hi) / 2)[:, None] * dd, c, h)
                best[i, j] = np.minimum(best[i, j], mid)
            out[s : s + chunk] = best.min(axis=1)
    return out.reshape(shape)


def segment_hits_boxes(a: np.ndarray, b: np.ndarray, centers: np.ndarray, half_sizes: np.ndarray, tol: float) -> bool:
    """Whether the one segment [a, b] (d,) meets any box grown by ``tol`` on every side (:func:`segments_hit_boxes`).
    The boxes grown by ``tol`` per axis contain those grown by ``tol`` in Euclidean distance, so this answers
    ``segment_box_distance(a, b) < tol`` except within ``tol * sqrt(d)`` of an edge."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return bool(segments_hit_boxes(a[None], b[None], centers, half_sizes, tol)[0])


def segments_hit_boxes(
    a: np.ndarray, b: np.ndarray, centers: np.ndarray, half_sizes: np.ndarray, tol: float = 0.0, chunk: int = 8192
) -> np.ndarray:
    """Boolean over segments [a, b] (..., d): whether each meets a closed box grown by ``tol`` on every side, by the
    slab test, exact and closed-form (the segment's parameter interval inside each box is the intersection of its
    intervals between each pair of faces): a segment that only touches a box's corner or edge meets it."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    shape = a.shape[:-1]
    fa, fd = a.reshape(-1, a.shape[-1]), (b - a).reshape(-1, a.shape[-1])
    out = np.zeros(fa.shape[0], dtype=bool)
    if len(centers) == 0:
        return out.reshape(shape)
    centers, half_sizes = np.asarray(centers, dtype=np.float64), np.asarray(half_sizes, dtype=np.float64)
    for s in range(0, fa.shape[0], chunk):
        p, d = fa[s : s + chunk, None, :], fd[s : s + chunk, None, :]
        low, high = centers - half_sizes - tol - p, centers + half_sizes + tol - p  # the faces, relative to a
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = low / d, high / d
        still = d == 0  # parallel to that pair of faces: inside the slab for every t, or never
        inside = (low <= 0) & (high >= 0)
        enter = np.where(still, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=-1)
        leave = np.where(still, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=-1)
        out[s : s + chunk] = np.any((enter <= leave) & (enter <= 1.0) & (leave >= 0.0), axis=-1)
    return out.reshape(shape)


def path_crosses_boxes(states: np.ndarray, obstacles: BoxObstacles) -> np.ndarray:
    """Boolean over paths (..., T, D): True where any state is in collision (:func:`in_boxes`) or any straight
    segment between consecutive states passes within ``obstacles.inflate`` of a box (a jump through a wall)."""
    states = np.asarray(states)
    pts = states[..., obstacles.dims].astype(np.float64)
    centers, halves = box_arrays(obstacles)
    a, b = pts[..., :-1, :], pts[..., 1:, :]
    if obstacles.inflate > 0:
        seg = segment_box_distance(a, b, centers, halves, obstacles.inflate) < obstacles.inflate
    else:  # a point agent: the exact test, as closed as in_boxes (a segment through the corner two boxes share)
        seg = segments_hit_boxes(a, b, centers, halves)
    return in_boxes(states, obstacles).any(axis=-1) | seg.any(axis=-1)


def largest_jump(states: np.ndarray, dims) -> np.ndarray:
    """The largest distance between consecutive states of each path (..., T, D), over ``dims``."""
    pts = np.asarray(states, dtype=np.float64)[..., list(dims)]
    if pts.shape[-2] < 2:
        return np.zeros(pts.shape[:-2])
    return np.linalg.norm(np.diff(pts, axis=-2), axis=-1).max(axis=-1)


def box_penetration(points, centers, half_sizes, inflate: float = 0.0):
    """How deep each point (torch, (..., d)) lies inside the nearest box grown by ``inflate`` on every side: for a
    box, the smallest of (half size + inflate - |p - c|) over the axes when all are positive, else 0; summed over
    the boxes (boxes seldom overlap). Differentiable almost everywhere: its gradient pushes a point out of a box
    along the shortest way, which is what collision-guided sampling follows."""
    from cdrb_cli.lazy import torch

    c = torch.as_tensor(centers, dtype=points.dtype, device=points.device)
    h = torch.as_tensor(half_sizes, dtype=points.dtype, device=points.device) + inflate
    if c.shape[0] == 0:
        return torch.zeros(points.shape[:-1], dtype=points.dtype, device=points.device)
    depth = h - (points[..., None, :] - c).abs()  # (..., M, d)
    return torch.relu(depth.min(dim=-1).values).sum(-1)
