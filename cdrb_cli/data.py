"""Training windows cut from demonstrations (task side).

A window is H planned states taken every ``stride`` environment steps from some offset of an episode; indices past
the episode's end repeat its final state (the expert at rest on the goal). So a window's last state is the state a
plan's goal is pinned to, and short episodes still fill a whole plan. Windows are drawn uniformly over all
(episode, offset) pairs of the split."""

from __future__ import annotations

import numpy as np

from cdrb_cli.buffer import Normalizer, demo_features
from cdrb_cli.errors import BadInput


def window_index(lengths, horizon: int, stride: int, offsets=0) -> np.ndarray:
    """(n, H) indices into n episodes of the given lengths: H states every ``stride`` steps from ``offsets``, indices
    past an episode's end repeating its last state."""
    lengths = np.asarray(lengths, dtype=np.int64)
    offsets = np.broadcast_to(np.asarray(offsets, dtype=np.int64), lengths.shape)
    idx = offsets[:, None] + stride * np.arange(horizon)[None, :]
    return np.minimum(idx, (lengths - 1)[:, None])


def first_window(states: np.ndarray, horizon: int, stride: int) -> np.ndarray:
    """The window of one episode's states (T, D) from its first state: what a plan from the episode's start spans."""
    return np.asarray(states)[window_index([len(states)], horizon, stride)[0]]


class WindowSampler:
    def __init__(
        self,
        demos,
        features: str,
        normalizer: Normalizer,
        horizon: int,
        stride: int,
        split: str = "train",
        start_fraction: float = 0.0,
    ):
        eps = demos.episode_ids(split)
        if len(eps) == 0:
            raise BadInput(f"{demos.path}: the {split!r} split has no episodes", hint="collect more episodes")
        feats = normalizer.normalize(demo_features(demos, features)).astype(np.float32)
        starts, lengths = demos.episode_start[eps].astype(np.int64), demos.episode_length[eps].astype(np.int64)
        if (lengths < 2).any():
            raise BadInput(f"{demos.path}: episodes must have at least 2 states", hint="re-collect the demos")
        self.flat = feats
        self.starts, self.lengths = starts, lengths
        self.horizon, self.stride = horizon, stride
        self.offsets = lengths - 1  # offsets 0 .. L-2 per episode: every window moves at least one step
        self.cum = np.cumsum(self.offsets)
        self.feature_dim = feats.shape[1]
        self.start_fraction = start_fraction

    @property
    def n_windows(self) -> int:
        return int(self.cum[-1])

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, H, F) normalized windows."""
        pair = rng.integers(0, self.n_windows, size=n)
        e = np.searchsorted(self.cum, pair, side="right")
        offset = pair - np.concatenate([[0], self.cum])[e]
        if self.start_fraction > 0:
            anchored = rng.random(n) < self.start_fraction
            e = np.where(anchored, rng.integers(0, len(self.starts), size=n), e)
            offset = np.where(anchored, 0, offset)
        idx = window_index(self.lengths[e], self.horizon, self.stride, offset) + self.starts[e][:, None]
        return self.flat[idx]

    def episode_windows(self, max_windows: int | None = None) -> np.ndarray:
        """One window per episode from its first state (the test-time situation), for validation."""
        n = len(self.starts) if max_windows is None else min(len(self.starts), max_windows)
        idx = window_index(self.lengths[:n], self.horizon, self.stride) + self.starts[:n, None]
        return self.flat[idx]
