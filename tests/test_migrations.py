"""Artifacts written by cdrb 0.1 (schema 1.x, tests/data/v1) are read through migrations and give the results they
gave then: the same plans, the same evaluation, and the same weights when retrained.

"The same" is exact for every discrete result (success, in-wall flags, step counts) and within float round-off for
real numbers: the files were written on one CPU, and another CPU's kernels (AVX2 vs AVX-512, oneDNN's choice of
algorithm) round float32 sums differently, so bit equality does not hold across machines (CI saw 6e-6 on plans).
The tolerances are far below what another seed changes (checked for the plans and the retrained weights)."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.configs import PlanConfig
from cdrb_cli.methods.config import train_config
from cdrb_cli.stages.evaluate import evaluate
from cdrb_cli.stages.plan import make_plans
from cdrb_cli.stages.train import train
from tests.factories import edit_manifest

V1 = Path(__file__).resolve().parent / "data" / "v1"
KINDS = ("demos", "buffer", "model", "plans", "eval")


@pytest.mark.parametrize("kind", KINDS)
def test_every_v1_kind_reads(kind):
    art = artifacts.load(V1 / f"{kind}.h5", kind)
    assert art.migrated_from is not None and art.migrated_from.startswith("1.")
    assert art.manifest.env.family == "pointmaze" and art.manifest.env.scene.maze.name == "maze-tight"
    assert art.manifest.env.pin_dims == [0, 1, 2, 3]


def test_v1_model_layout_is_per_module():
    m = artifacts.load(V1 / "model.h5")
    assert all(
        k.startswith(("weights/net/", "ema/net/", "optim/net/net/", "normalizer/", "curve/", "buffer/"))
        for k in m.arrays
    )
    steps = [v for k, v in m.arrays.items() if k.startswith("optim/") and k.endswith("/step")]
    assert steps and all(v.shape == () and v.dtype == np.float32 for v in steps)


def _same(new, old, key, rtol, atol):
    """Exact for integer/bool arrays, within round-off for floats."""
    new, old = np.asarray(new), np.asarray(old)
    assert new.shape == old.shape and new.dtype == old.dtype, key
    if np.issubdtype(old.dtype, np.floating):
        np.testing.assert_allclose(new, old, rtol=rtol, atol=atol, err_msg=key)
    else:
        np.testing.assert_array_equal(new, old, err_msg=key)


def test_v1_model_plans_as_before(tmp_path):
    model = artifacts.load(V1 / "model.h5")
    old = artifacts.load(V1 / "plans.h5")
    cfg = PlanConfig(sampler="paper", n=2, seed=3)  # "alg1" in the 1.x file, renamed in 2.2
    new = make_plans(model, old.starts.astype(np.float64), old.goals.astype(np.float64), cfg, tmp_path / "p.h5")
    _same(new.plans, old.plans, "plans", rtol=1e-4, atol=1e-4)
    _same(new.arrays["in_wall"], old.arrays["in_wall"], "in_wall", 0, 0)
    # the tolerance discriminates: another sampling seed moves the plans by far more than it
    other = make_plans(
        model,
        old.starts.astype(np.float64),
        old.goals.astype(np.float64),
        PlanConfig(sampler="paper", n=2, seed=4),
        tmp_path / "q.h5",
    )
    assert np.abs(other.plans - old.plans).max() > 1e-2


def test_v1_model_evaluates_as_before(tmp_path):
    model = artifacts.load(V1 / "model.h5")
    old = artifacts.load(V1 / "eval.h5")
    assert old.manifest.config.controller.name == "pd" and old.manifest.config.controller.max_lag == 0.6
    new = evaluate(model, old.manifest.config, tmp_path / "e.h5")
    added = {"episodes/plan_crosses_obstacle", "episodes/plan_max_jump", "episodes/plan_step_limit"}  # 2.2 metrics
    added |= {"episodes/replans", "episodes/planning_seconds"}  # 2.4: closed-loop planning
    added |= {"episodes/failure"}  # 2.5: failures by cause
    added |= {"episodes/plan_states", "episodes/plan_first_step"}  # 2.18: what report measures on plans
    assert new.arrays.keys() == old.arrays.keys() | added
    # the 2.4 and 2.5 datasets are back-filled when the 1.x file is read: one plan per episode, failures unclassified
    assert (old.arrays["episodes/replans"] == 0).all() and (old.arrays["episodes/failure"] == -1).all()
    np.testing.assert_array_equal(old.arrays["episodes/planning_seconds"], old.arrays["episodes/plan_seconds"])
    for key in old.arrays:
        if key not in ("episodes/plan_seconds", "episodes/planning_seconds", "episodes/failure"):  # times; classified
            _same(new.arrays[key], old.arrays[key], key, rtol=1e-5, atol=1e-5)
    # the same config and model, but an eval from before schema 2.2 lacks the plan-crossing measurements: redone
    found = artifacts.existing(V1 / "eval.h5", "eval", old.manifest.config, [model])
    assert found.status == "different" and "measured less" in found.reason


def test_retraining_the_v1_config_gives_the_v1_weights(tmp_path):
    demos, buffer = artifacts.load(V1 / "demos.h5"), artifacts.load(V1 / "buffer.h5")
    old = artifacts.load(V1 / "model.h5")
    settings = {"steps": 4, "checkpoint_every": 2, "net.dim": 8, "net.dim_mults": [1], "horizon": 16, "stride": 10}
    old_cdrb = {"method.diffusion_steps": 4, "method.end_actions": "kept", "checkpoint_seconds": 0.0}  # as migrated
    old_cdrb["method.ball_candidates"] = "fixed"
    cfg = train_config(demos, buffer, "cdrb", {**settings, **old_cdrb, "batch_size": 4})
    assert cfg == old.manifest.config
    new = train(demos, buffer, cfg, tmp_path / "m.h5")
    assert new.arrays.keys() == old.arrays.keys()
    for key in old.arrays:
        # four Adam steps amplify round-off where a gradient is near zero (CI saw 1.5e-3 on a bias)
        _same(new.arrays[key], old.arrays[key], key, rtol=0, atol=1e-2)
    # ...which is far below what another seed's initialisation gives
    other = train(demos, buffer, cfg.model_copy(update={"seed": cfg.seed + 1}), tmp_path / "m2.h5")
    moved = [np.abs(other.arrays[k] - old.arrays[k]).max() for k in old.arrays if k.startswith("weights/")]
    assert max(moved) > 1e-1


def test_eval_1_0_had_no_gated_clock(tmp_path):
    """eval 1.1 added max_lag; a 1.0 file (no such field) followed plans on the environment's clock."""
    p = tmp_path / "e.h5"
    shutil.copy(V1 / "eval.h5", p)
    with h5py.File(p, "r+") as f:
        edit_manifest(f, lambda m: (m["config"].pop("max_lag"), m.update(schema_version="1.0")))
        f.attrs["cdrb_schema_version"] = "1.0"
    art = artifacts.load(p, "eval")
    assert art.migrated_from == "1.0" and art.manifest.config.controller.max_lag is None


def test_cli_reads_v1_files(tmp_path, cdrb):
    r = cdrb("inspect", V1 / "model.h5")
    assert r.returncode == 0 and "read through a migration" in r.stdout
    r = cdrb("plan", V1 / "model.h5", "--start", "0,0", "--goal", "6,6", "--out", tmp_path / "p.h5")
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("version, schedule, sampler", [("2.1", "geometric", "paper"), ("2.2", "log", "paper")])
def test_2_2_renames(tmp_path, version, schedule, sampler):
    """Schema 2.2 renamed CDRB's log-spaced schedule "log" to "geometric" (log is now the official code's) and the
    samplers alg1/alg2 to paper/cold-improved: an older file reads with the new names, a 2.2 file as written."""
    from tests.factories import tampered, write

    path = write(tmp_path / "m.h5", "model")
    with tampered(path) as f:

        def edit(m):
            m["schema_version"] = version
            m["config"]["method"]["schedule"] = "log"
            if version == "2.1":  # as a 2.1 file was: the old sampler name, no end_actions field
                m["config"]["method"]["sampler"] = "alg1"
                del m["config"]["method"]["end_actions"]

        edit_manifest(f, edit)
        f.attrs["cdrb_schema_version"] = version
    method = artifacts.load(path, "model").manifest.config.method
    assert (method.schedule, method.sampler) == (schedule, sampler)
    assert method.end_actions == ("kept" if version == "2.1" else "degraded")


def test_a_2_2_file_reads_with_the_goal_pinned_like_the_start(tmp_path):
    """Schema 2.3 added env.pinned_end_dims; a 2.2 file has no such field and keeps its meaning (null: the goal pins
    what the start pins)."""
    from tests.factories import tampered, write

    path = write(tmp_path / "m.h5", "model")
    with tampered(path) as f:
        edit_manifest(f, lambda m: (m.update(schema_version="2.2"), m["env"].pop("pinned_end_dims")))
        f.attrs["cdrb_schema_version"] = "2.2"
    env = artifacts.load(path, "model").manifest.env
    assert env.pinned_end_dims is None and env.pin_end_dims == env.pin_dims


def test_fetch_scenes_before_the_goal_distance_rule_read_as_drawn(tmp_path):
    """Fetch scenes gained ``min_goal_distance`` (goals kept 7 cm from the start) in demos/buffer/model/plans 2.4
    and eval 2.6; an older file's scene drew goals at any distance and reads as 0, a current one as written."""
    from cdrb_cli.artifacts.migrations import migrate_minor
    from cdrb_cli.envs.registry import make_spec

    scene = make_spec("fetch-push-obstacle").scene.model_dump(mode="json")
    old = {k: v for k, v in scene.items() if k != "min_goal_distance"}
    for kind, version in (("demos", (2, 3)), ("eval", (2, 5))):
        m = migrate_minor(kind, version, {"env": {"scene": old}})
        assert m["env"]["scene"]["min_goal_distance"] == 0.0
    kept = migrate_minor("model", (2, 3), {"env": {"scene": {**scene, "min_goal_distance": 0.09}}})
    assert kept["env"]["scene"]["min_goal_distance"] == 0.09
    maze = {"env": {"scene": {"family": "pointmaze"}}}
    assert migrate_minor("demos", (2, 3), maze) == maze


def test_geodesic_models_before_matched_radii_read_as_scaled_and_euclidean_ones_as_they_are():
    """Model 2.14 matched geodesic radii to the paper's ball sizes: an older geodesic model stretched its schedule to
    the graph's diameter and reads as ``scaled``; an older Euclidean model, which reads no geodesic radii, keeps the
    default, so it still equals a new request's config (a grid does not train it again)."""
    from cdrb_cli.artifacts.migrations import migrate_minor

    geo = {"config": {"method": {"name": "cdrb", "ball": "geodesic"}}}
    assert migrate_minor("model", (2, 13), geo)["config"]["method"]["geodesic_radii"] == "scaled"
    assert "geodesic_radii" not in migrate_minor("model", (2, 14), geo)["config"]["method"]
    for euclidean in ({"name": "cdrb", "ball": "euclidean"}, {"name": "cdrb"}):
        m = {"config": {"method": euclidean}}
        assert migrate_minor("model", (2, 13), m) == m


def test_evals_of_geodesic_models_before_matched_radii_name_the_scaled_variant():
    """Eval 2.17: an older eval of a geodesic model evaluated the scaled radii and says so when read."""
    from cdrb_cli.artifacts.migrations import migrate_minor

    for old, new in [
        ("geodesic balls", "geodesic balls, scaled radii"),
        ("geodesic balls, d_max of the data box", "geodesic balls, scaled radii, d_max of the data box"),
    ]:
        assert migrate_minor("eval", (2, 16), {"summary": {"variant": old}})["summary"]["variant"] == new
        assert migrate_minor("eval", (2, 17), {"summary": {"variant": old}})["summary"]["variant"] == old
    for kept in ({"summary": {"variant": None}}, {"summary": {"variant": "d_max of the data box"}}):
        assert migrate_minor("eval", (2, 16), kept) == kept
