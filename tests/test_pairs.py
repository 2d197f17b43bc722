"""The start/goal pairs every protocol stream draws: no episode is won at reset, and the Fetch obstacle tasks
draw only pairs that must get past the wall."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli.envs.fetch import TASKS
from cdrb_cli.envs.fetch.tasks import side
from cdrb_cli.envs.registry import FAMILIES, family_of, make_spec
from cdrb_cli.seeding import STREAM_EVAL, STREAM_TUNE

STOCK = [i for fam in FAMILIES.entries() for i in fam.env_ids()]
STREAMS = {"test": STREAM_EVAL, "tuning": STREAM_TUNE}
N = 40


@pytest.mark.parametrize("env_id", STOCK)
@pytest.mark.parametrize("stream", sorted(STREAMS))
def test_no_pair_is_won_at_reset(env_id, stream):
    """Reset every drawn episode in the simulator: the reset state is never within the success radius of its goal
    (two eval seeds, as a table's seeds would draw)."""
    spec = make_spec(env_id)
    fam = family_of(spec)
    for seed in (0, 1):
        eps = fam.draw_episodes(spec, N, seed, STREAMS[stream])
        starts, goals = fam.reset_states(spec, eps)
        won = fam.success(spec, starts, goals)
        assert not won.any(), f"{env_id} {stream} seed {seed}: episodes {np.flatnonzero(won).tolist()} won at reset"


@pytest.mark.parametrize("env_id", [i for i, t in TASKS.items() if t[1] and not i.endswith("-mixed")])
def test_obstacle_pairs_all_cross_the_wall(env_id):
    """Push / Pick & Place: block and goal on opposite sides of the wall; Reach: the goal outside the corridor the
    gripper starts in, as the simulator resets them."""
    spec = make_spec(env_id)
    fam = family_of(spec)
    eps = fam.draw_episodes(spec, 60, 0, STREAM_EVAL)
    starts, goals = fam.reset_states(spec, eps)
    for s, g in zip(starts, goals):
        start = s[spec.goal_dims]
        if spec.scene.task == "reach":
            assert side(spec.scene, start) == 0 and side(spec.scene, g) != 0
        else:
            assert side(spec.scene, start) * side(spec.scene, g) == -1


def test_mixed_draws_keep_both_sides():
    """The -mixed ids keep goals on the block's side of the wall too (a draw the crossing ids never make)."""
    spec = make_spec("fetch-push-obstacle-mixed")
    fam = family_of(spec)
    eps = fam.draw_episodes(spec, 60, 0, STREAM_EVAL)
    same = [side(spec.scene, np.array(e.start + (0.0,))) == side(spec.scene, np.array(e.goal)) for e in eps]
    assert 0 < sum(same) < len(same)
