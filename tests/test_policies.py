"""Closed-loop policies: the transition data, Diffusion BC's training and acting, closed-loop eval."""

from __future__ import annotations

import types

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.methods.config import train_config
from cdrb_cli.stages.train import train
from tests.factories import RandomActions

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


def test_relabelled_goals_lie_a_geometric_number_of_steps_ahead(small_data):
    """With relabel_horizon h a relabelled goal is min(t + G, last) with G ~ Geometric(1/h) on 1, 2, ...: the
    offsets' sum matches that law's (a z-test summed over each sample's cut), and the uniform law fails the same
    test, so it can tell them apart."""
    from cdrb_cli.buffer import Normalizer, demo_features
    from cdrb_cli.data import TransitionSampler

    demos, _ = small_data
    raw = demo_features(demos, "state-action")
    ident = Normalizer(low=-np.ones(raw.shape[1], np.float32), high=np.ones(raw.shape[1], np.float32))
    row_of = {row.tobytes(): i for i, row in enumerate(raw.astype(np.float32))}
    episode = np.repeat(np.arange(len(demos.episode_length)), demos.episode_length)
    last = (demos.episode_start + demos.episode_length - 1)[episode]
    h, n = 4.0, 4000

    def z_of(horizon):
        batch = TransitionSampler(demos, "state-action", ident, 1, "all", 1.0, horizon).sample(
            n, np.random.default_rng(2)
        )
        t = np.array([row_of[b[0].tobytes()] for b in batch])
        goal = np.array([row_of[b[-1].tobytes()] for b in batch])
        cut, d = last[t] - t, goal - t
        assert (d >= 1).all() and (d <= cut).all() and (episode[goal] == episode[t]).all()
        mean = var = 0.0
        for c in cut:  # min(G, c): P(j) = p (1-p)^(j-1) for j < c, the rest of the mass at c
            p = 1 / h
            pmf = p * (1 - p) ** np.arange(c)
            pmf[-1] = (1 - p) ** (c - 1)
            j = np.arange(1, c + 1)
            m = (pmf * j).sum()
            mean, var = mean + m, var + (pmf * (j - m) ** 2).sum()
        return (d.sum() - mean) / np.sqrt(var)

    assert abs(z_of(h)) < 4
    assert abs(z_of(None)) > 8


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


def _corridor_demos(tmp_path):
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.stages.collect import collect, collect_config

    m = tmp_path / "corridor.txt"
    m.write_text(CORRIDOR)
    spec = make_spec(None, m)
    return spec, collect(spec, collect_config(spec, episodes=60, seed=0), tmp_path / "d.h5")


def _random_policy_success(spec, episodes: int) -> float:
    """Success of uniform random actions on the first tuning episodes (seed 0) of ``spec``."""
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.seeding import STREAM_TUNE
    from cdrb_cli.stages.evaluate import run_policy

    family = family_of(spec)
    pairs = family.draw_episodes(spec, episodes, 0, STREAM_TUNE)
    runs, _, _ = run_policy(
        family, spec, pairs, RandomActions(spec.action_dim), spec.episode_limit, np.random.default_rng(0)
    )
    return float(np.mean([run.success for run in runs]))


def _closed_loop_beats_random(model, spec, tmp_path, cdrb) -> None:
    """Closed loop on 20 tuning episodes the policy succeeds >= 60% and 30 points above random actions; the eval
    writes no plan measures, refuses a controller flag and reports "closed loop" with n/a."""
    r = cdrb("eval", model.path, "--stream", "tune", "--seeds", "0", "--episodes", "20", "--out", tmp_path / "e.h5")
    assert r.returncode == 0, r.stderr
    ev = artifacts.load(tmp_path / "e.h5", "eval")
    assert "episodes/plan_in_wall_fraction" not in ev.arrays and ev.manifest.summary.in_wall_mean is None
    random_success = _random_policy_success(spec, 20)
    success = ev.manifest.summary.success_mean
    assert success >= 0.6 and success > random_success + 0.3, (success, random_success)
    r = cdrb("eval", model.path, "--controller", "pd", "--out", tmp_path / "e2.h5")
    assert r.returncode == 2 and "policy" in r.stderr and not (tmp_path / "e2.h5").exists()
    r = cdrb("report", tmp_path / "e.h5")
    assert r.returncode == 0 and "closed loop" in r.stdout and "n/a" in r.stdout


@pytest.mark.slow
def test_diffusion_bc_learns_the_loss_and_beats_a_random_policy(tmp_path, cdrb):
    """On a small corridor maze: over 600 updates the loss falls, and closed loop the policy reaches the goal far more
    often than uniform random actions on the same episodes (400 updates pass too, so the budget has a margin)."""
    spec, demos = _corridor_demos(tmp_path)
    cfg = train_config(demos, None, "diffusion-bc", {"steps": 600, "net.embed_dim": 32, "net.hidden": 128})
    model = train(demos, None, cfg, tmp_path / "bc.h5")
    loss = model.arrays["curve/loss"]
    assert loss[-3:].mean() < 0.6 * loss[:3].mean()
    _closed_loop_beats_random(model, spec, tmp_path, cdrb)


@pytest.mark.slow
def test_diffusion_ql_beats_a_random_policy(tmp_path, cdrb):
    """The same corridor: over 700 updates of Diffusion-QL (BC + Q term, sparse success reward) the actor's BC
    loss falls, and it acts far better than random actions (measured: 100% of 20 episodes; 65% after 450
    updates, so the budget has a margin)."""
    spec, demos = _corridor_demos(tmp_path)
    settings = {"steps": 700, "net.hidden": [128] * 3, "batch_size": 64, "lr": 1e-3}
    cfg = train_config(demos, None, "diffusion-ql", settings)
    model = train(demos, None, cfg, tmp_path / "ql.h5")
    loss = model.arrays["curve/loss"]  # the actor's BC (DDPM) term
    assert loss[-3:].mean() < 0.6 * loss[:3].mean()
    _closed_loop_beats_random(model, spec, tmp_path, cdrb)


TINY_QL = {"net.hidden": [16, 16], "batch_size": 8, "lr": 1e-3}


def _ql(demos, **settings):
    from cdrb_cli.buffer import Normalizer
    from cdrb_cli.methods.base import build_method

    cfg = train_config(demos, None, "diffusion-ql", {**TINY_QL, **settings})
    from cdrb_cli.stages.train import check_inputs

    norm: Normalizer = check_inputs(demos, None, cfg.features)
    return build_method(cfg, demos.manifest.env, norm), cfg


def test_diffusion_ql_reward_and_critic_target_follow_their_definition(small_data):
    """r = 1 exactly when the next state passes the env's success test (then terminal, tuned to (r - 0.5) * 4);
    the target is r + gamma (1 - done) min_i max_j Q_i'(s', a'_j) with a'_j from the EMA actor; Polyak targets."""
    import torch

    from cdrb_cli.seeding import torch_generator

    demos, _ = small_data
    torch.manual_seed(0)
    method, cfg = _ql(demos)
    batch = torch.from_numpy(method.data(demos, method.normalizer, "train").sample(64, np.random.default_rng(3)))
    batch[:5, -1] = batch[:5, 1]  # five goals at their next state: success
    r, done = method.reward(batch)
    raw = method.normalizer.unnormalize(batch.numpy().astype(np.float64))
    spec = demos.manifest.env
    dist = np.linalg.norm(raw[:, 1, spec.goal_dims] - raw[:, -1, spec.goal_dims], axis=1)
    np.testing.assert_array_equal(done[:, 0].numpy(), (dist <= spec.success_radius).astype(np.float32))
    assert done[:5].all() and not done.all()
    np.testing.assert_allclose(r[:, 0].numpy(), (done[:, 0].numpy() - 0.5) * 4)
    _, _, nxt = method._parts(batch)
    target = method.critic_target(nxt, r, done, torch_generator(np.random.default_rng(9)))
    with torch.no_grad():  # by hand: the same draws of next actions, 10 per next state
        rep = nxt.repeat_interleave(10, dim=0)
        a = method._sample(method.targets.actor, rep, torch_generator(np.random.default_rng(9)))
        q1, q2 = method.targets.critic(rep, a)
        best = torch.min(q1.view(-1, 10).max(1)[0], q2.view(-1, 10).max(1)[0])[:, None]
    np.testing.assert_allclose(target.numpy(), (r + cfg.method.gamma * (1 - done) * best).numpy(), rtol=1e-5)
    assert torch.equal(target[:5], r[:5])  # terminal: no bootstrap
    # one update: the critic targets move by tau towards the critic, the EMA actor copies before ema_start
    before = [p.clone() for p in method.targets.critic.parameters()]
    method.update(batch, np.random.default_rng(0), method.make_optimizers())
    tau = cfg.method.tau
    for old, new, cur in zip(before, method.targets.critic.parameters(), method.critic.parameters()):
        torch.testing.assert_close(new, (1 - tau) * old + tau * cur)
    for ema, cur in zip(method.targets.actor.parameters(), method.actor.parameters()):
        assert torch.equal(ema, cur)
    assert int(method.targets.updates) == 1


@pytest.mark.parametrize("reward_tune", ["none", "cql-antmaze"])
@pytest.mark.parametrize("gamma", [0.5, 0.9, 0.99])
def test_return_bounds_are_the_least_and_greatest_discounted_return(reward_tune, gamma):
    """Every episode of the sparse reward (n failures, then success or never) has its return inside the bounds,
    and the bounds are reached (never, or success at once)."""
    from cdrb_cli.methods.diffusion_ql import return_bounds, reward_values

    r_s, r_f = reward_values(reward_tune)
    returns = [sum(r_f * gamma**i for i in range(n)) + gamma**n * r_s for n in range(3000)]
    returns.append(sum(r_f * gamma**i for i in range(3000)))  # never succeeds (the tail is below 1e-9 here)
    lo, hi = return_bounds(reward_tune, gamma)
    assert lo <= min(returns) + 1e-9 and max(returns) <= hi + 1e-9
    assert min(returns) == pytest.approx(lo, abs=1e-6) and max(returns) == pytest.approx(hi, abs=1e-6)


@pytest.mark.parametrize("bias", [1e4, -1e4])
def test_target_clip_keeps_the_critic_target_inside_the_return_bounds(small_data, bias):
    """A target critic that overestimates (or underestimates) without bound gives bootstrap targets outside the
    returns the reward allows; with target_clip they are clipped to the bounds, terminal targets untouched."""
    import torch

    from cdrb_cli.methods.diffusion_ql import return_bounds
    from cdrb_cli.seeding import torch_generator

    demos, _ = small_data
    targets = {}
    for clip in (False, True):
        torch.manual_seed(0)
        method, cfg = _ql(demos, **{"method.target_clip": clip})
        with torch.no_grad():
            for head in (method.targets.critic.q1, method.targets.critic.q2):
                head[-1].bias.fill_(bias)
        batch = torch.from_numpy(method.data(demos, method.normalizer, "train").sample(64, np.random.default_rng(3)))
        batch[:5, -1] = batch[:5, 1]  # five goals at their next state: success, terminal
        r, done = method.reward(batch)
        _, _, nxt = method._parts(batch)
        targets[clip] = method.critic_target(nxt, r, done, torch_generator(np.random.default_rng(9)))
    lo, hi = return_bounds(cfg.method.reward_tune, cfg.method.gamma)
    live = done[:, 0] == 0
    raw, clipped = targets[False][live], targets[True][live]
    assert ((raw > hi) if bias > 0 else (raw < lo)).all()  # the unclipped target leaves the bounds
    torch.testing.assert_close(clipped, raw.clamp(lo, hi))
    assert torch.equal(targets[True][~live], r[~live]) and torch.equal(targets[False][~live], r[~live])


def test_resume_of_diffusion_ql_is_exact_with_both_optimizers_and_targets(small_data, tmp_path):
    demos, _ = small_data
    flags = {**TINY_QL, "checkpoint_every": 10, "method.ema_start": 5, "method.ema_every": 2}
    full = train(demos, None, train_config(demos, None, "diffusion-ql", {**flags, "steps": 30}), tmp_path / "a.h5")
    train(demos, None, train_config(demos, None, "diffusion-ql", {**flags, "steps": 20}), tmp_path / "b.h5")
    rest = train_config(demos, None, "diffusion-ql", {**flags, "steps": 30})
    resumed = train(demos, None, rest, tmp_path / "b.h5", resume=True)
    keys = {k for k in full.arrays if k.startswith(("weights/", "optim/"))}
    assert keys == {k for k in resumed.arrays if k.startswith(("weights/", "optim/"))}
    assert {k.split("/")[1] for k in keys if k.startswith("optim/")} == {"actor", "critic"}
    assert any(k.startswith("weights/targets/") for k in keys) and "weights/targets/updates" in keys
    for k in keys:
        np.testing.assert_array_equal(full.arrays[k], resumed.arrays[k], err_msg=k)
    assert float(full.arrays["weights/targets/updates"]) == 30


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_bfloat16_runs_the_forward_passes_of_an_update_and_keeps_the_weights_float32(small_data, precision):
    """precision=bfloat16: every forward pass of a Diffusion-QL update (critic, target, BC loss, the actor's
    differentiable chain) runs its hidden linear layers in bfloat16 and the critics' value layers in float32;
    weights and optimizer state stay float32, and the update's loss is the float32 one up to bfloat16 rounding."""
    import torch

    demos, _ = small_data
    seen = []
    runs = {}
    for p in dict.fromkeys(["float32", precision]):
        torch.manual_seed(0)
        method, _ = _ql(demos, precision=p)
        heads = {id(c.q1[-1]) for c in (method.critic, method.targets.critic)}
        heads |= {id(c.q2[-1]) for c in (method.critic, method.targets.critic)}
        hooks = [
            m.register_forward_hook(
                lambda mod, inp, out, p=p, h=heads: seen.append((p, "value" if id(mod) in h else "hidden", out.dtype))
            )
            for net in (method.actor, method.critic, method.targets.actor, method.targets.critic)
            for m in net.modules()
            if isinstance(m, torch.nn.Linear)
        ]
        batch = torch.from_numpy(method.data(demos, method.normalizer, "train").sample(32, np.random.default_rng(3)))
        opts = method.make_optimizers()
        loss = method.update(batch, np.random.default_rng(0), opts)
        for h in hooks:
            h.remove()
        assert np.isfinite(loss)
        params = [*method.actor.parameters(), *method.critic.parameters(), *method.targets.parameters()]
        assert all(q.dtype == torch.float32 for q in params if q.is_floating_point())
        assert all(s["exp_avg"].dtype == torch.float32 for o in opts.values() for s in o.state.values())
        runs[p] = loss
    hidden = {d for p, kind, d in seen if p == precision and kind == "hidden"}
    assert hidden == {torch.bfloat16 if precision == "bfloat16" else torch.float32}
    # the critics' values stay float32: bfloat16 steps by 1.0 near the tuned rewards' Q of ~-200
    assert {d for p, kind, d in seen if p == precision and kind == "value"} == {torch.float32}
    assert runs[precision] == pytest.approx(runs["float32"], rel=0.05)


def test_bfloat16_is_refused_on_a_gpu_without_it_and_said_to_be_emulated_on_a_cpu(monkeypatch):
    import torch

    from cdrb_cli import ui
    from cdrb_cli.errors import BadInput
    from cdrb_cli.stages import train as train_stage
    from cdrb_cli.stages.train import check_precision

    cfg = types.SimpleNamespace(precision="bfloat16")
    warned = []
    monkeypatch.setattr(ui, "warn", warned.append)
    for native in (True, False):  # a CPU runs it, natively or emulated: the emulated case is said
        monkeypatch.setattr(train_stage, "native_cpu_bfloat16", lambda native=native: native)
        check_precision(cfg, "cpu")
        assert len(warned) == (0 if native else 1)
    assert "no native bfloat16" in warned[0] and "precision=float32" in warned[0]
    check_precision(types.SimpleNamespace(precision="float32"), "cpu")
    assert len(warned) == 1
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda: False)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "Tesla V100")
    with pytest.raises(BadInput, match="precision=bfloat16: Tesla V100 has no bfloat16"):
        check_precision(cfg, "cuda")
    check_precision(types.SimpleNamespace(precision="float32"), "cuda")
