"""Training windows cut from demonstrations (task side): whole-plan windows for planners, transitions with a goal
for policies (:class:`TransitionSampler`).

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


#: the most a window may span, in multiples of the longest demonstration: past it, over three quarters of every
#: window repeats an episode's last state, and a horizon or stride that large is a typo
MAX_SPAN_EPISODES = 4


def check_window_span(demos, horizon: int, stride: int) -> None:
    """Refuse a window of ``horizon`` states every ``stride`` steps that spans more than :data:`MAX_SPAN_EPISODES`
    times the longest episode of ``demos`` (before a network is sized for the horizon)."""
    longest = int(np.max(demos.episode_length, initial=0))
    span = (horizon - 1) * stride
    if longest >= 2 and span > MAX_SPAN_EPISODES * (longest - 1):
        spec = demos.manifest.env
        raise BadInput(
            f"horizon {horizon} x stride {stride}: a window spans {span} steps, over {MAX_SPAN_EPISODES} times the "
            f"longest demonstration in {demos.path} ({longest} states), so most of every window would repeat the goal",
            hint=f"lower horizon or stride; this env's defaults are horizon={spec.horizon}, stride={spec.plan_stride}",
        )


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

    def validation_batch(self, n: int = 64) -> np.ndarray:
        """The fixed batch the validation loss is measured on."""
        return self.episode_windows(n)


class TransitionSampler(WindowSampler):
    """What a goal-conditioned policy learns from: (n, H + 1, F) rows, the first H the state-action features of H
    consecutive steps from a uniformly drawn step t (the chunk of actions to predict from the state at t; indices
    past the episode's end repeat its last row), the last the features of the *goal state*: the episode's final
    state, or with probability ``relabel`` a later state of the same episode (hindsight relabelling, "future"):
    uniform over the rest of the episode, or with ``relabel_horizon`` h the state a Geometric(1/h) number of steps
    ahead (mean h, cut at the episode's end), as goal-conditioned RL samples goals with a discount 1 - 1/h; goals
    near the present are then as common as the near goals (waypoints) a policy is given when it acts. The expert
    reaches its goal, so the final state stands for the commanded goal."""

    def __init__(
        self,
        demos,
        features: str,
        normalizer: Normalizer,
        horizon: int,
        split: str = "train",
        relabel=0.0,
        relabel_horizon: float | None = None,
    ):
        super().__init__(demos, features, normalizer, horizon, 1, split)
        self.relabel = float(relabel)
        self.relabel_horizon = relabel_horizon

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        pair = rng.integers(0, self.n_windows, size=n)
        e = np.searchsorted(self.cum, pair, side="right")
        t = pair - np.concatenate([[0], self.cum])[e]  # 0 .. L-2
        last = self.lengths[e] - 1
        if self.relabel_horizon is None:
            future = t + 1 + np.floor(rng.random(n) * (last - t)).astype(np.int64)  # uniform in t+1 .. L-1
        else:  # t + Geometric(1/h) on 1, 2, ..., cut at L-1
            future = np.minimum(t + rng.geometric(1.0 / self.relabel_horizon, size=n), last)
        goal = np.where(rng.random(n) < self.relabel, future, last)
        idx = window_index(self.lengths[e], self.horizon, 1, t)
        idx = np.concatenate([idx, goal[:, None]], axis=1) + self.starts[e][:, None]
        return self.flat[idx]

    def validation_batch(self, n: int = 256) -> np.ndarray:
        return self.sample(n, np.random.default_rng(0))
