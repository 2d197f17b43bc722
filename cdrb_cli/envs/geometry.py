"""Generic obstacle geometry: axis-aligned boxes over some state dimensions, distances to them, and the collision
test of :class:`cdrb_cli.envs.spec.BoxObstacles` (vectorized over any batch of states)."""

from __future__ import annotations

import numpy as np

from cdrb_cli.envs.spec import BoxObstacles


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


def in_boxes(states: np.ndarray, obstacles: BoxObstacles) -> np.ndarray:
    """Boolean mask over states (..., D): True where the agent (a ball of radius ``obstacles.inflate`` centred at
    the state's obstacle dimensions) overlaps a box, or its centre lies outside ``[low, high]``."""
    states = np.asarray(states)
    pts = states[..., obstacles.dims].astype(np.float64)
    centers, halves = box_arrays(obstacles)
    hit = box_distance(pts, centers, halves) < obstacles.inflate
    low, high = np.asarray(obstacles.low), np.asarray(obstacles.high)
    outside = np.any((pts < low) | (pts > high), axis=-1)
    return hit | outside
