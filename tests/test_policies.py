"""Closed-loop policies (issue #17): the transition data, Diffusion BC's training and acting, closed-loop eval."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.methods.config import train_config
from cdrb_cli.stages.train import train

TINY_BC = {"net.embed_dim": 16, "net.hidden": 32, "method.diffusion_steps": 8, "batch_size": 8, "lr": 2e-3}
CORRIDOR = "#######\n#S...G#\n#.###.#\n#.....#\n#######\n"


def test_transitions_hold_a_chunk_from_a_step_and_a_goal_of_the_same_episode(small_data):
    """Rows 0..H-1: H consecutive steps (held at the episode's end); the last row: the episode's final state, or
    with relabel = 1 a strictly later state of the same episode."""
    from cdrb_cli.buffer import Normalizer, demo_features
    from cdrb_cli.data import TransitionSampler

    demos, _ = small_data
    raw = demo_features(demos, "state-action")
    ident = Normalizer(low=-np.ones(raw.shape[1], np.float32), high=np.ones(raw.shape[1], np.float32))
    flat = raw.astype(np.float32)
    row_of = {row.tobytes(): i for i, row in enumerate(flat)}  # demo rows are distinct (continuous states)
    episode = np.repeat(np.arange(len(demos.episode_length)), demos.episode_length)
    last = (demos.episode_start + demos.episode_length - 1)[episode]
    for relabel in (0.0, 1.0):
        batch = TransitionSampler(demos, "state-action", ident, 3, "all", relabel).sample(500, np.random.default_rng(1))
        assert batch.shape == (500, 4, raw.shape[1])
        rows = np.array([[row_of[r.tobytes()] for r in b] for b in batch])
        t = rows[:, 0]
        assert (rows[:, 1] == np.minimum(t + 1, last[t])).all() and (rows[:, 2] == np.minimum(t + 2, last[t])).all()
        assert (episode[rows[:, 3]] == episode[t]).all() and (t < last[t]).all()
        if relabel == 0.0:
            assert (rows[:, 3] == last[t]).all()
        else:
            assert (rows[:, 3] > t).all() and (rows[:, 3] < last[t]).mean() > 0.5  # uniform over later states


def test_resume_of_diffusion_bc_is_exact(small_data, tmp_path):
    demos, _ = small_data
    full = train(
        demos,
        None,
        train_config(demos, None, "diffusion-bc", {**TINY_BC, "steps": 40, "checkpoint_every": 10}),
        tmp_path / "a.h5",
    )
    train(
        demos,
        None,
        train_config(demos, None, "diffusion-bc", {**TINY_BC, "steps": 20, "checkpoint_every": 10}),
        tmp_path / "b.h5",
    )
    rest = train_config(demos, None, "diffusion-bc", {**TINY_BC, "steps": 40, "checkpoint_every": 10})
    resumed = train(demos, None, rest, tmp_path / "b.h5", resume=True)
    wa = {k: v for k, v in full.arrays.items() if k.startswith(("weights/", "ema/", "optim/"))}
    wb = {k: v for k, v in resumed.arrays.items() if k.startswith(("weights/", "ema/", "optim/"))}
    assert wa.keys() == wb.keys() and any(k.startswith("optim/") for k in wa)
    for k in wa:
        np.testing.assert_array_equal(wa[k], wb[k], err_msg=k)


def test_diffusion_bc_config_needs_actions_and_fits_its_chunk(small_data):
    from cdrb_cli.errors import BadInput

    demos, _ = small_data
    cfg = train_config(demos, None, "diffusion-bc")
    assert cfg.features == "state-action" and cfg.horizon == 1 and cfg.net.kind == "sieve"
    with pytest.raises(BadInput, match="state-action"):
        train_config(demos, None, "diffusion-bc", {"features": "state"})
    with pytest.raises(BadInput, match="horizon"):
        train_config(demos, None, "mlp", {"horizon": 1})  # a plan needs a start and a goal


@pytest.mark.slow
def test_diffusion_bc_learns_the_loss_and_beats_a_random_policy(tmp_path, cdrb):
    """On a small corridor maze: the loss falls, and closed loop the policy reaches the goal far more often than
    uniform random actions on the same episodes; the eval reports no plan measures and refuses a controller."""
    from cdrb_cli.envs.registry import family_of, make_spec
    from cdrb_cli.seeding import STREAM_TUNE
    from cdrb_cli.stages.collect import collect, collect_config
    from cdrb_cli.stages.evaluate import run_policy

    m = tmp_path / "corridor.txt"
    m.write_text(CORRIDOR)
    spec = make_spec(None, m)
    demos = collect(spec, collect_config(spec, episodes=60, seed=0), tmp_path / "d.h5")
    cfg = train_config(demos, None, "diffusion-bc", {"steps": 1500, "net.embed_dim": 32, "net.hidden": 128})
    model = train(demos, None, cfg, tmp_path / "bc.h5")
    loss = model.arrays["curve/loss"]
    assert loss[-3:].mean() < 0.6 * loss[:3].mean()
    r = cdrb("eval", model.path, "--stream", "tune", "--seeds", "0", "--episodes", "20", "--out", tmp_path / "e.h5")
    assert r.returncode == 0, r.stderr
    ev = artifacts.load(tmp_path / "e.h5", "eval")
    assert "episodes/plan_in_wall_fraction" not in ev.arrays and ev.manifest.summary.in_wall_mean is None

    class Random:
        def reset(self, n, rng):
            pass

        def act(self, states, goals, rng):
            return rng.uniform(-1, 1, size=(len(states), spec.action_dim))

    family = family_of(spec)
    episodes = family.draw_episodes(spec, 20, 0, STREAM_TUNE)
    runs, _, _ = run_policy(family, spec, episodes, Random(), spec.episode_limit, np.random.default_rng(0))
    random_success = np.mean([run.success for run in runs])
    assert ev.manifest.summary.success_mean >= 0.6 and ev.manifest.summary.success_mean > random_success + 0.3, (
        ev.manifest.summary.success_mean,
        random_success,
    )
    r = cdrb("eval", model.path, "--controller", "pd", "--out", tmp_path / "e2.h5")
    assert r.returncode == 2 and "policy" in r.stderr and not (tmp_path / "e2.h5").exists()
    r = cdrb("report", tmp_path / "e.h5")
    assert r.returncode == 0 and "closed loop" in r.stdout and "n/a" in r.stdout
