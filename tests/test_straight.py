"""The straight-line planner: the floor every planner must beat. It learns nothing, its model has no weights, and
it plans, evaluates and reports like any other method, on every family."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.envs.registry import FAMILIES, family_of
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.checkpoint import load_method
from cdrb_cli.methods.config import train_config
from cdrb_cli.stages.train import train


def test_its_plan_is_the_straight_line_and_its_model_has_no_weights(small_data, tmp_path):
    import torch

    demos, _ = small_data
    cfg = train_config(demos, None, "straight", {})
    assert cfg.steps == 50  # its own default: it only measures the line's error
    model = train(demos, None, cfg, tmp_path / "s.h5")
    assert model.manifest.state.parameters == 0 and model.manifest.state.finished
    assert not [k for k in model.arrays if k.startswith(("weights/", "ema/", "optim/"))]
    loss = model.arrays["curve/loss"]
    assert np.isfinite(loss).all() and loss.min() > 0  # the demonstrations are not straight lines

    method = load_method(model)
    start = torch.tensor([[-0.5, 0.2, 0.1, -0.1], [0.3, 0.3, 0.0, 0.0]])
    goal = torch.tensor([[0.5, -0.4, 0.0, 0.0], [-0.9, 0.7, 0.2, 0.2]])
    plans = method.sample(start, goal, np.random.default_rng(0)).plans
    h = method.horizon
    assert plans.shape == (2, h, method.feature_dim)
    w = torch.linspace(0, 1, h)[None, :, None]
    torch.testing.assert_close(plans, start[:, None] * (1 - w) + goal[:, None] * w)
    assert torch.equal(plans[:, 0], start) and torch.equal(plans[:, -1], goal)  # pinned exactly
    # its loss is the line's L2 error on a batch of windows, recomputed here from the definition
    batch = torch.randn(3, h, method.feature_dim)
    line = batch[:, :1] * (1 - w) + batch[:, -1:] * w
    assert float(method.loss(batch, None)) == pytest.approx(float(((line - batch) ** 2).mean()), rel=1e-6)


def test_only_a_model_with_no_parameters_may_have_no_weights(small_data, tmp_path):
    demos, _ = small_data
    model = train(demos, None, train_config(demos, None, "straight", {}), tmp_path / "s.h5")
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert "weights" not in f and model.manifest.state.parameters == 0
    # a network's model without its weights (written with a valid checksum) is refused
    mlp = train(demos, None, train_config(demos, None, "mlp", {"steps": 2, "batch_size": 4}), tmp_path / "m.h5")
    arrays = {k: v for k, v in mlp.arrays.items() if not k.startswith(("weights/", "ema/", "optim/"))}
    artifacts.save(tmp_path / "n.h5", "model", mlp.manifest, arrays)
    n = mlp.manifest.state.parameters
    with pytest.raises(BadInput, match=f"no datasets under /weights/, but the model has {n} parameters"):
        artifacts.load(tmp_path / "n.h5")


STOCK = [i for fam in FAMILIES.entries() for i in fam.env_ids() if not i.endswith("-mixed")]


@pytest.mark.slow
@pytest.mark.parametrize("env", STOCK)
def test_it_trains_plans_evaluates_and_reports_through_the_cli(env, tmp_path, cdrb):
    """On every stock env, under each of its protocols (the official executor's early end included)."""
    demos, model, ev = tmp_path / "d.h5", tmp_path / "m.h5", tmp_path / "e.h5"
    assert cdrb("collect", env, "-n", "6", "--out", demos).returncode == 0
    assert cdrb("train", demos, "--method", "straight", "--out", model).returncode == 0
    proc = cdrb("eval", model, "--seeds", "0", "--episodes", "3", "--stream", "tune", "--out", ev)
    assert proc.returncode == 0, proc.stderr
    e = artifacts.load(ev, "eval")
    plans = e.arrays["plans"]
    steps = np.diff(plans, axis=1)
    np.testing.assert_allclose(steps, np.broadcast_to(steps[:, :1], steps.shape), atol=1e-4)  # equal steps: a line
    proc = cdrb("report", ev, "--format", "json")
    assert proc.returncode == 0 and '"method": "straight"' in proc.stdout
    spec = e.manifest.env
    family = family_of(spec)
    for protocol in family.extra_protocols:
        out = tmp_path / f"e-{protocol}.h5"
        proc = cdrb(
            "eval", model, "--seeds", "0", "--episodes", "2", "--stream", "tune", "--protocol", protocol, "--out", out
        )
        if protocol in family.scene_protocols:  # pairs of a changed scene: refused in the training scene
            assert proc.returncode == 2 and "runs in the" in proc.stderr and not out.exists(), proc.stderr
            assert "--maze-map" in proc.stderr or "--scene" in proc.stderr, proc.stderr
            continue
        assert proc.returncode == 0, proc.stderr
        assert artifacts.load(out, "eval").manifest.config.protocol == protocol
