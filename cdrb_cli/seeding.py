"""Seeds: every random choice in cdrb derives from the command's ``--seed`` through numpy SeedSequences, so that
an episode, a training step or an evaluation is reproducible from (seed, stream, index) alone."""

from __future__ import annotations

import numpy as np

# distinct streams so that, e.g., evaluation episodes never reuse the demonstrations' start/goal draws
STREAM_COLLECT = 1
STREAM_EVAL = 2
STREAM_TRAIN = 3
STREAM_PLAN = 4
STREAM_CLUSTER = 5
STREAM_VALID = 6
STREAM_TUNE = 7
STREAM_REPLAN = 8
STREAM_EVAL_PLAN = 9

#: `cdrb eval --stream`: the start/goal pairs every knob is chosen on ("tune") are drawn from their own stream, so
#: the pairs of the reported tables ("test") are never seen while choosing anything (docs/design.md)
EVAL_STREAMS = {"test": STREAM_EVAL, "tune": STREAM_TUNE}


def episode_seeds(seed: int, n: int, stream: int) -> np.ndarray:
    """``n`` 31-bit seeds for episodes 0..n-1 of ``stream`` under ``seed``."""
    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, stream])
    return ss.generate_state(max(n, 1), dtype=np.uint64)[:n].astype(np.int64) & 0x7FFFFFFF


def step_rng(seed: int, stream: int, step: int) -> np.random.Generator:
    """A fresh generator for one step (training step, planning batch...), independent of what ran before."""
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, stream, int(step)]))


def eval_plan_seed(seed: int, eval_seed: int) -> int:
    """The seed of an eval's first plans for the pairs of ``eval_seed`` under the run's ``seed`` (`--seed`): the pair
    seed itself at seed 0, the default (so evals made before ``--seed`` reached these plans read the same), else a
    32-bit word drawn from both."""
    if int(seed) == 0:
        return int(eval_seed)
    words = [int(seed) & 0xFFFFFFFF, STREAM_EVAL_PLAN, int(eval_seed) & 0xFFFFFFFF]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


def replan_rng(seed: int, eval_seed: int, group: int, step: int) -> np.random.Generator:
    """The generator of one re-planning call of closed-loop evaluation (eval seed, group of episodes, env step)."""
    words = [int(seed) & 0xFFFFFFFF, STREAM_REPLAN, int(eval_seed) & 0xFFFFFFFF, int(group), int(step)]
    return np.random.default_rng(np.random.SeedSequence(words))


def torch_generator(rng: np.random.Generator, device="cpu"):
    import torch

    g = torch.Generator(device=device)
    g.manual_seed(int(rng.integers(0, 2**63 - 1)))
    return g
