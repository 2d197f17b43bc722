"""The benchmark scripts run end to end on tiny settings (the same code paths as the recorded runs)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_latency_script_times_each_tree_and_its_fast_paths_beside_plan_safety(tmp_path, small_data):
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    model = train(demos, buffer, train_config(demos, buffer, "cdrb", tiny("cdrb", steps=10)), tmp_path / "m.h5")
    cmd = [sys.executable, str(ROOT / "benchmarks" / "latency.py"), str(model.path), "--pairs", "4", "--plans", "2",
           "--batches", "1,3", "--rounds", "1", "--threads", "1", "--variants", "--markdown",
           "--tree", f"now={ROOT}"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [line.split(" | ") for line in proc.stdout.splitlines() if line.startswith("| now")]
    assert [r[0] for r in rows] == ["| now", "| now, fast paths off"]
    for r in rows:
        ms1, ms3, in_obstacle, through = (float(v.strip(" |")) for v in r[3:7])
        assert ms1 > 0 and ms3 > 0 and 0 <= in_obstacle <= 100 and 0 <= through <= 100
    assert rows[0][5:] == rows[1][5:]  # the fast paths plan the same plans: the same safety figures


def test_policy_actions_draws_held_out_expert_transitions_and_scores_agreement(small_data):
    """policy_actions.py: the transitions come from validation episodes only, with the episode's final state as
    goal and the expert's own action (the first-step set: each validation episode's first row); the expert scores
    error 0 / cosine 1, its reverse cosine -1 (every action off), a half-strength copy keeps the direction and has
    norm ratio 0.5."""
    from benchmarks.policy_actions import agreement, first_steps, held_out
    from cdrb_cli.buffer import Normalizer, demo_features

    demos, _ = small_data
    raw = demo_features(demos, "state-action")
    norm = Normalizer(low=raw.min(axis=0), high=raw.max(axis=0))
    obs_dim, goal_dims = demos.manifest.env.obs_dim, list(demos.manifest.env.goal_dims)
    states, goals, actions = held_out(demos, norm, obs_dim, goal_dims, 300, 0)
    valid = set(demos.episode_ids("valid").tolist())
    assert valid and len(valid) < len(demos.episode_length)
    episode = np.repeat(np.arange(len(demos.episode_length)), demos.episode_length)
    last = demos.episode_start + demos.episode_length - 1
    # each drawn (state, action) is a demonstration row of a validation episode, its goal that episode's final state
    dist = np.abs(raw[None, :, :obs_dim] - states[:, None]).max(axis=2)
    row = dist.argmin(axis=1)
    assert dist[np.arange(len(row)), row].max() < 1e-4
    np.testing.assert_allclose(raw[row, obs_dim:], actions, atol=1e-4)
    assert set(episode[row].tolist()) <= valid
    np.testing.assert_allclose(raw[last[episode[row]]][:, goal_dims], goals, atol=1e-4)
    # the first-step set: every validation episode's first row, at rest, its goal the episode's final state
    s0, g0, a0 = first_steps(demos, obs_dim, goal_dims)
    ids = demos.episode_ids("valid")
    np.testing.assert_array_equal(s0, raw[demos.episode_start[ids], :obs_dim])
    np.testing.assert_array_equal(a0, raw[demos.episode_start[ids], obs_dim:])
    np.testing.assert_array_equal(g0, raw[last[ids]][:, goal_dims])

    same = agreement(actions, actions)
    assert same["mean_abs_error"] == 0 and same["median_cosine"] == 1 and same["off_by_25deg"] == 0
    assert same["norm_ratio"] == 1
    rev = agreement(-actions, actions)
    assert rev["median_cosine"] == -1 and rev["off_by_25deg"] == 1
    half = agreement(0.5 * actions, actions)
    assert half["median_cosine"] == 1 and half["norm_ratio"] == 0.5 and half["off_by_25deg"] == 0


def test_policy_actions_measures_every_sampler_a_policy_allows_and_refuses_a_planner(small_data, tmp_path):
    """policy_actions.py's `measure`: one row per set and per sampler the method's config allows (the model's own
    first); a planner's model is a one-line error."""
    from benchmarks.policy_actions import measure
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train

    demos, _ = small_data
    tiny = {"net.embed_dim": 16, "net.hidden": 32, "method.diffusion_steps": 4, "batch_size": 8, "steps": 2}
    cfg = train_config(demos, None, "diffusion-bc", {**tiny, "method.sampler": "ddpm"})
    train(demos, None, cfg, tmp_path / "bc.h5")
    rows = measure(tmp_path / "bc.h5", 16, 0)
    assert [(r["set"], r["sampler"]) for r in rows] == [
        (s, sampler) for s in ("transitions", "first step") for sampler in ("ddpm", "ddpm-x")
    ]
    assert rows[0]["pairs"] == 16 and 0 <= rows[0]["off_by_25deg"] <= 1
    mlp = train_config(demos, None, "mlp", {"steps": 2, "batch_size": 8})
    train(demos, None, mlp, tmp_path / "mlp.h5")
    with pytest.raises(SystemExit, match="mlp.h5: mlp is a planner"):
        measure(tmp_path / "mlp.h5", 16, 0)
