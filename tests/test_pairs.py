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
#: pairs per seed under a protocol that simulates each start (Fetch from anywhere drives the arm there twice: when
#: drawn and at reset, ~0.06 s each): 360 simulated starts over its 18 cases; their block and goal are the stock
#: draws, checked at N above
N_SIMULATED = 10


#: (env id, protocol) of every stock env under every protocol that draws its own starts
DRAWS = [(i, None) for i in STOCK] + [
    (i, p) for fam in FAMILIES.entries() for i in fam.env_ids() for p in fam.start_protocols
]


@pytest.mark.parametrize("env_id,protocol", DRAWS)
@pytest.mark.parametrize("stream", sorted(STREAMS))
def test_no_pair_is_won_at_reset(env_id, protocol, stream):
    """Reset every drawn episode in the simulator: the reset state is never within the success radius of its goal
    (two eval seeds, as a table's seeds would draw)."""
    spec = make_spec(env_id)
    fam = family_of(spec)
    n = N_SIMULATED if protocol == "anywhere" and spec.family == "fetch" else N
    for seed in (0, 1):
        eps = fam.draw_protocol_episodes(spec, n, seed, STREAMS[stream], protocol)
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


@pytest.mark.parametrize("env_id", [i for i in STOCK if family_of(make_spec(i)).name == "pointmaze"])
def test_anywhere_draws_start_in_free_cells_beyond_the_start_region(env_id):
    """Mazes: `anywhere` starts cover the free cells (not only the protocol's start cells), every goal is a goal
    cell reachable from its start, and the draw is the same for the same seed (Fetch's: test_fetch.py)."""
    from cdrb_cli.envs.pointmaze.maze import MazeGeometry

    spec = make_spec(env_id)
    fam = family_of(spec)
    geom = MazeGeometry(spec.scene.maze)
    eps = fam.draw_protocol_episodes(spec, 400, 0, STREAM_EVAL, "anywhere")
    assert eps == fam.draw_protocol_episodes(spec, 400, 0, STREAM_EVAL, "anywhere")
    starts = {e.start for e in eps}
    protocol_starts = {tuple(c) for c in geom.start_cells.tolist()}
    goals = {tuple(c) for c in geom.goal_cells.tolist()}
    assert all(geom.free[s] for s in starts)
    if len(protocol_starts) < int(geom.free.sum()) / 2:  # a start region (Maze Tight: the centre): mostly outside it
        assert len(starts - protocol_starts) > len(starts) / 2
    assert len(starts) > 0.5 * int(geom.free.sum())  # and spread over the free cells
    for e in eps:
        assert e.goal in goals and e.goal != e.start and geom.bfs(e.goal)[e.start] >= 0
