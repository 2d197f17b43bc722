"""Training: the loss decreases, checkpoints resume bit for bit (also after SIGKILL), bad inputs are refused."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.config import train_config
from cdrb_cli.stages.train import train
from tests.conftest import call_cdrb

#: tiny settings of the diffusion methods (U-Net), and of the MLP
TINY = {"net.dim": 8, "net.dim_mults": [1, 2], "horizon": 16, "method.diffusion_steps": 8, "batch_size": 8, "lr": 2e-3}
TINY_MLP = {"horizon": 16, "batch_size": 8, "lr": 2e-3}
TINY_FLAGS = [
    *("--set", "net.dim=8"),
    *("--set", "net.dim_mults=1,2"),
    *("--set", "horizon=16"),
    *("--set", "method.diffusion_steps=8"),
    *("--set", "batch_size=8"),
    *("--set", "lr=2e-3"),
    *("--device", "cpu"),
]


def tiny(method: str, **settings) -> dict:
    """The tiny settings of ``method`` plus ``settings``."""
    return {**(TINY_MLP if method == "mlp" else TINY), **settings}


def _weights(model):
    return {k: v for k, v in model.arrays.items() if k.startswith(("weights/", "ema/", "optim/"))}


def test_cdrb_learns_to_restore(small_data, tmp_path):
    """After a short training the restorer beats two baselines on held-out windows at mid and large k: the
    identity (returning the degraded input) and the straight line from start to goal."""
    import torch

    from cdrb_cli.data import WindowSampler
    from cdrb_cli.methods.checkpoint import load_method

    demos, buffer = small_data
    # stride 10: a 16-state window spans 160 env steps, long enough to turn through the maze
    # the paper's plain set-up (no residual output, unweighted loss): the test is about learning to restore
    plain = {"net.residual": False, "method.loss_weight_power": 0.0}
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=600, checkpoint_every=200, stride=10, **plain))
    model = train(demos, buffer, cfg, tmp_path / "m.h5")
    loss = model.arrays["curve/loss"]
    assert model.manifest.state.finished and model.manifest.state.step == 600
    assert loss[-5:].mean() < loss[:5].mean()
    assert "buffer/points" in model.arrays and model.arrays["buffer/points"].shape == buffer.points.shape
    assert [p.kind for p in model.manifest.parents] == ["demos", "buffer"]
    method = load_method(model)  # the EMA weights
    tau = torch.from_numpy(
        WindowSampler(demos, "state", method.normalizer, cfg.horizon, cfg.stride, "valid").episode_windows()
    )
    rng = np.random.default_rng(0)
    start, goal = method.ends(tau, method.obs_dim)
    w = torch.linspace(0, 1, tau.shape[1])[None, :, None]
    line = start[:, None] * (1 - w) + goal[:, None] * w
    err_line = float(((line - tau[..., : method.obs_dim]) ** 2).mean())
    for k in (4, 6, 7):
        noisy = method.pin(method._degrade(tau, k, rng), start, goal)
        with torch.no_grad():
            pred = method.pin(method.net(noisy, torch.full((len(tau),), k)), start, goal)
        err_model = float(((pred - tau) ** 2).mean())
        err_identity = float(((noisy - tau) ** 2).mean())
        assert err_model < 0.5 * err_identity and err_model < err_line, (k, err_model, err_identity, err_line)


@pytest.mark.parametrize("method", ["cdrb", "diffuser", "mlp"])
def test_resume_continues_to_the_same_result(small_data, tmp_path, method):
    demos, buffer = small_data
    b = buffer if method == "cdrb" else None
    full = train(
        demos, b, train_config(demos, b, method, tiny(method, steps=40, checkpoint_every=20)), tmp_path / "a.h5"
    )
    # a finished shorter run, ended between two checkpoints of the longer one (on its loss curve: every 10 steps)
    half = train_config(demos, b, method, tiny(method, steps=30, checkpoint_every=20))
    train(demos, b, half, tmp_path / "b.h5")
    rest = train_config(demos, b, method, tiny(method, steps=40, checkpoint_every=20))
    resumed = train(demos, b, rest, tmp_path / "b.h5", resume=True)
    wa, wb = _weights(full), _weights(resumed)
    assert wa.keys() == wb.keys()
    for k in wa:
        np.testing.assert_array_equal(wa[k], wb[k], err_msg=k)
    for name in ("curve/step", "curve/loss", "curve/valid_step", "curve/valid_loss"):
        np.testing.assert_array_equal(full.arrays[name], resumed.arrays[name], err_msg=name)
    assert list(full.arrays["curve/valid_step"]) == [20, 40]


def test_resume_refuses_an_optimizer_tensor_of_the_wrong_shape(small_data, tmp_path):
    """A checkpoint whose Adam moment no longer has its parameter's shape is refused, naming the tensor, before
    the optimizer is handed it (PyTorch would index past the tensor's memory at the next step)."""
    demos, buffer = small_data
    train(
        demos,
        buffer,
        train_config(demos, buffer, "cdrb", tiny("cdrb", steps=20, checkpoint_every=10)),
        tmp_path / "m.h5",
    )
    model = artifacts.load(tmp_path / "m.h5")
    arrays = dict(model.arrays)
    key = next(k for k in arrays if k.startswith("optim/") and k.endswith("/exp_avg") and arrays[k].size > 1)
    arrays[key] = arrays[key].reshape(-1)[:-1].copy()
    artifacts.save(tmp_path / "m.h5", "model", model.manifest, arrays)
    rest = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=40, checkpoint_every=10))
    with pytest.raises(BadInput, match=f"optimizer tensor /{key} has shape"):
        train(demos, buffer, rest, tmp_path / "m.h5", resume=True)


@pytest.fixture(scope="module")
def uninterrupted(small_data, tmp_path_factory):
    """The 300-step training the kill-and-resume cases must reproduce, run once and never checkpointed: weights do
    not depend on when a run checkpoints (the by-time case's checkpoints fall at other steps in every run)."""
    demos, buffer = small_data
    out = tmp_path_factory.mktemp("uninterrupted") / "ref.h5"
    never = ["--set", "checkpoint_every=100000", "--set", "checkpoint_seconds=0"]
    r = call_cdrb("train", demos.path, "--buffer", buffer.path, "--steps", "300", *never, *TINY_FLAGS, "--out", out)
    assert r.returncode == 0, r.stderr
    model = artifacts.load(out)
    assert model.manifest.state.finished and model.manifest.state.step == 300
    return model


@pytest.mark.parametrize(
    "checkpoints",
    [
        ["--set", "checkpoint_every=10", "--set", "checkpoint_seconds=0"],  # by steps only
        ["--set", "checkpoint_every=100000", "--set", "checkpoint_seconds=0.3"],  # by time only (none by steps)
    ],
    ids=["by-steps", "by-time"],
)
def test_kill_and_resume_matches_uninterrupted(small_data, uninterrupted, tmp_path, cdrb, checkpoints):
    demos, buffer = small_data
    args = ["train", demos.path, "--buffer", buffer.path, "--steps", "300", *checkpoints, *TINY_FLAGS]
    out = tmp_path / "killed.h5"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", *map(str, args), "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=dict(os.environ),
    )
    step = 0
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
        if out.exists():
            try:
                step = artifacts.load(out, "model").manifest.state.step
            except BadInput:
                continue  # never happens with atomic writes; tolerated only while polling
            if step >= 60:
                break
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = artifacts.load(out, "model").manifest.state
    assert not killed_at.finished and 60 <= killed_at.step < 300, killed_at
    assert not [p for p in tmp_path.iterdir() if p.name.startswith("killed.h5") and p.name != "killed.h5"]
    r = cdrb(*args, "--out", out)  # without --resume an unfinished checkpoint is not overwritten
    assert r.returncode == 2 and "--resume" in r.stderr
    r = cdrb(*args, "--out", out, "--resume")
    assert r.returncode == 0, r.stderr
    a, b = _weights(uninterrupted), _weights(artifacts.load(out))
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # re-running the finished command is a no-op
    r = cdrb(*args, "--out", out)
    assert r.returncode == 0 and "up to date" in r.stderr


def test_nan_loss_stops_and_keeps_last_checkpoint(small_data, tmp_path, monkeypatch):
    import torch

    from cdrb_cli.errors import RunFailed
    from cdrb_cli.methods.cdrb import CDRB

    demos, buffer = small_data
    out = tmp_path / "m.h5"
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=30, checkpoint_every=10))
    real = CDRB.loss
    calls = {"n": 0}

    def poisoned(self, batch, rng):
        loss = real(self, batch, rng)
        if not torch.is_grad_enabled():  # validation losses at checkpoints
            return loss
        calls["n"] += 1
        return loss * torch.tensor(float("nan")) if calls["n"] == 25 else loss

    monkeypatch.setattr(CDRB, "loss", poisoned)
    with pytest.raises(RunFailed, match="diverged at step 25") as err:
        train(demos, buffer, cfg, out)
    assert "keeps the last good checkpoint (step 20)" in err.value.message and "--resume" in err.value.hint
    kept = artifacts.load(out, "model")
    assert kept.manifest.state.step == 20 and not kept.manifest.state.finished
    assert all(np.all(np.isfinite(v)) for v in _weights(kept).values())
    # diverged before the first checkpoint: nothing to resume, and the error says so
    calls["n"] = 20
    with pytest.raises(RunFailed, match="diverged at step 5") as err:
        train(demos, buffer, cfg, tmp_path / "none.h5")
    assert "no checkpoint was written" in err.value.message and "--resume" not in err.value.hint
    assert not (tmp_path / "none.h5").exists()
    # a run that writes over another model (--force) and diverges before its own first checkpoint: the file is
    # still the other model, not a checkpoint of this run to resume
    calls["n"] = 20
    with pytest.raises(RunFailed, match="diverged at step 5") as err:
        train(demos, buffer, cfg, out)
    assert "no checkpoint was written" in err.value.message and "--resume" not in err.value.hint, err.value.line()


def test_refuses_mismatched_buffer(small_data, tmp_path):
    from cdrb_cli.configs import ClusterConfig
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.stages.cluster import cluster
    from cdrb_cli.stages.collect import collect, collect_config

    demos, buffer = small_data
    spec = make_spec("maze")
    other = collect(spec, collect_config(spec, episodes=6, seed=1), tmp_path / "other.h5")
    other_buf = cluster(other, ClusterConfig(k=20, seed=0), tmp_path / "ob.h5")
    cfg = train_config(demos, other_buf, "cdrb", tiny("cdrb", steps=5))
    with pytest.raises(BadInput, match="made for env 'maze'"):
        train(demos, other_buf, cfg, tmp_path / "m.h5")
    spec_t = make_spec("maze-tight")
    other_t = collect(spec_t, collect_config(spec_t, episodes=6, seed=5), tmp_path / "other_t.h5")
    buf_t = cluster(other_t, ClusterConfig(k=20, seed=0), tmp_path / "obt.h5")
    with pytest.raises(BadInput, match="normalizer does not match"):
        train(demos, buf_t, train_config(demos, buf_t, "cdrb", tiny("cdrb", steps=5)), tmp_path / "m2.h5")


def test_config_errors(small_data):
    demos, buffer = small_data
    with pytest.raises(BadInput, match="a multiple of 2"):
        train_config(demos, buffer, "cdrb", tiny("cdrb", horizon=15))
    with pytest.raises(BadInput, match="needs --buffer"):
        train_config(demos, None, "cdrb")
    with pytest.raises(BadInput, match="steps=-3: Input should be greater than 0"):
        train_config(demos, buffer, "cdrb", {"steps": -3})
    with pytest.raises(BadInput, match="unknown setting 'method.schedule'"):
        train_config(demos, None, "mlp", {"method.schedule": "log"})  # a CDRB setting is no MLP setting
    with pytest.raises(BadInput, match="the mlp method uses --net mlp"):
        train_config(demos, None, "mlp", {"net.kind": "unet"})


def test_cli_train_bad_flags(small_data, tmp_path, cdrb):
    demos, buffer = small_data
    cases = [
        (["--steps", "-1"], "--steps"),
        (["--steps", str(10**20)], "--steps 100000000000000000000: Input should be less than or equal to"),
        (["--set", "horizon=30", "--set", "net.dim_mults=1,2,4"], "multiple of 4"),
        (["--method", "magic"], "--method"),
        (["--set", "method.schedule=cubic"], "--set method.schedule=cubic: Input should be"),
        (["--set", "net.dimm=3"], "unknown setting 'net.dimm'"),
        (["--set", "net.dim"], "expected KEY=VALUE"),
        (["--horizon", "30"], "--set horizon=VALUE"),  # the pre-0.2 flags point to their config field
        (["--set", "net.kernel_size=4"], "must be odd"),
        (["--set", "horizon=100000000000000000000000"], "less than or equal to 100000"),
        (["--set", "stride=1000000000000000000"], "--set stride=1000000000000000000: Input should be less than"),
        # a window far past the longest demonstration: refused before a network is sized for it
        (["--set", "horizon=96000"], "most of every window would repeat the goal"),
        (["--set", "stride=100000"], "stride 100000: a window spans"),
        (["--set", "method.loss_weight_power=1000"], "--set method.loss_weight_power=1000: Input should be less"),
        (["--set", "method.d_max=1e300"], "--set method.d_max=1e300: Input should be less"),
        (["--seed", str(2**70)], "--seed"),
        (["--seed", "-1"], "--seed"),
        (["--buffer", demos.path], "'demos' artifact"),
        (["--method", "diffusion-bc"], "clustered on 'state' features, but this training uses 'state-action'"),
    ]
    for extra, needle in cases:
        args = ["train", demos.path, "--out", tmp_path / "m.h5"]
        if "--buffer" not in extra:
            args += ["--buffer", buffer.path]
        r = cdrb(*args, *extra)
        assert r.returncode == 2 and needle in r.stderr, (extra, r.stderr)
        assert r.stderr.count("\n") == 1
    assert not any(tmp_path.iterdir())


def test_snapshots_are_exactly_shorter_runs(small_data, tmp_path, cdrb):
    """`--snapshot-at` writes, mid-run, the model a run of that many steps writes: same weights, optimizer state,
    curve and config; the later run then skips it as up to date."""
    demos, buffer = small_data
    args = ["train", demos.path, "--buffer", buffer.path, "--set", "checkpoint_every=40", *TINY_FLAGS]
    out = tmp_path / "long.h5"
    r = cdrb(*args, "--steps", "80", "--snapshot-at", "20,60", "--out", out)
    assert r.returncode == 0, r.stderr
    for s in (20, 60):
        snap = artifacts.load(tmp_path / f"long.step{s}.h5", "model")
        ref_path = tmp_path / f"ref{s}.h5"
        assert cdrb(*args, "--steps", str(s), "--out", ref_path).returncode == 0
        ref = artifacts.load(ref_path, "model")
        assert snap.manifest.config == ref.manifest.config and snap.manifest.state.finished
        assert snap.manifest.state.step == s and snap.manifest.state.valid_loss == ref.manifest.state.valid_loss
        a, b = _weights(snap), _weights(ref)
        a.update({k: v for k, v in snap.arrays.items() if k.startswith("curve/")})
        b.update({k: v for k, v in ref.arrays.items() if k.startswith("curve/")})
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        r = cdrb(*args, "--steps", str(s), "--out", tmp_path / f"long.step{s}.h5")
        assert r.returncode == 0 and "up to date" in r.stderr
    # the long run itself is what it would be without snapshots
    plain = tmp_path / "plain.h5"
    assert cdrb(*args, "--steps", "80", "--out", plain).returncode == 0
    long = artifacts.load(out).arrays
    for k, v in artifacts.load(plain).arrays.items():
        np.testing.assert_array_equal(v, long[k], err_msg=k)
    # a finished 60-step run extended to 80 with --resume: the same final model, and the 60-step model kept as
    # the snapshot at 60 (a curve lengthened after the fact)
    ext = tmp_path / "ext.h5"
    assert cdrb(*args, "--steps", "60", "--out", ext).returncode == 0
    r = cdrb(*args, "--steps", "80", "--snapshot-at", "60", "--resume", "--out", ext)
    assert r.returncode == 0 and "resuming" in r.stderr, r.stderr
    # (the same weights, optimizer state and training loss; its validation curve also has the shorter run's last point)
    extended = artifacts.load(ext).arrays
    for k, v in artifacts.load(plain).arrays.items():
        if k != "curve/valid_loss" and k != "curve/valid_step":
            np.testing.assert_array_equal(v, extended[k], err_msg=k)
    kept = artifacts.load(tmp_path / "ext.step60.h5", "model")
    assert kept.manifest.config == artifacts.load(tmp_path / "ref60.h5").manifest.config
    for k, v in _weights(artifacts.load(tmp_path / "ref60.h5")).items():
        np.testing.assert_array_equal(v, _weights(kept)[k], err_msg=k)
    # bad snapshot steps, and an existing snapshot file without --force
    for bad, dry in [(b, d) for b in ("80", "0", "35", "x") for d in ([], ["--dry-run"])]:  # a dry run refuses them too
        r = cdrb(*args, "--steps", "80", "--snapshot-at", bad, "--out", tmp_path / "b.h5", *dry)
        assert r.returncode == 2 and "--snapshot-at" in r.stderr and len(r.stderr.strip().splitlines()) <= 2, bad
    (tmp_path / "new.step20.h5").write_bytes(b"mine")
    r = cdrb(*args, "--steps", "80", "--snapshot-at", "20", "--out", tmp_path / "new.h5")
    assert r.returncode == 2 and "new.step20.h5 exists and is not this run's snapshot" in r.stderr
    assert not (tmp_path / "new.h5").exists()


def test_snapshots_asked_for_after_the_run_passed_them_are_one_run_of_that_length(small_data, tmp_path, cdrb):
    """Earlier points added to a finished curve: the run is left as it is and one run from the start to the last
    of them writes them all, each the model `--steps N` writes; asked again, nothing is trained."""
    demos, buffer = small_data
    args = ["train", demos.path, "--buffer", buffer.path, "--set", "checkpoint_every=40", *TINY_FLAGS]
    out = tmp_path / "long.h5"
    assert cdrb(*args, "--steps", "80", "--out", out).returncode == 0
    refs = {s: tmp_path / f"ref{s}.h5" for s in (20, 60)}
    for s, ref in refs.items():
        assert cdrb(*args, "--steps", str(s), "--out", ref).returncode == 0
    before = artifacts.sha256_file(out)

    def check(extra: list[str], snaps: str, trained: str | None) -> None:
        r = cdrb(*args, "--steps", "80", "--snapshot-at", snaps, *extra, "--out", out)
        assert r.returncode == 0, r.stderr
        if trained is None:
            assert "from the start" not in r.stderr and "snapshots trained" not in r.stderr, r.stderr
        else:
            assert f"--snapshot-at {trained}: long.h5 was past" in r.stderr and "from the start" in r.stderr, r.stderr
            assert r.stderr.count("from the start") == 1  # one run for all of them
        assert artifacts.sha256_file(out) == before
        for s in map(int, snaps.split(",")):
            snap, ref = artifacts.load(tmp_path / f"long.step{s}.h5", "model"), artifacts.load(refs[s], "model")
            assert snap.manifest.config == ref.manifest.config and snap.manifest.state.finished
            assert snap.manifest.state.step == s
            for k, v in _weights(ref).items():
                np.testing.assert_array_equal(v, _weights(snap)[k], err_msg=(s, k))
        assert not list(tmp_path.glob(".long.e*.h5"))  # no hidden checkpoint left

    check(["--resume"], "20,60", "20,60")  # as a grid asks: its model is there
    check(["--resume"], "20,60", None)  # asked again: both are there
    (tmp_path / "long.step20.h5").unlink()
    check([], "20,60", "20")  # as a user asks, the run up to date: only the missing one
    # a file at a snapshot path that is not this run's snapshot: refused, with --resume too, before any work
    (tmp_path / "long.step20.h5").unlink()
    ref20 = artifacts.sha256_file(refs[20])
    for extra in ([], ["--resume"]):
        (tmp_path / "long.step20.h5").write_bytes(b"mine")
        r = cdrb(*args, "--steps", "80", "--snapshot-at", "20", *extra, "--out", out)
        assert r.returncode == 2 and "long.step20.h5 exists and is not this run's snapshot" in r.stderr, r.stderr
        assert "--force" in r.stderr
        assert (tmp_path / "long.step20.h5").read_bytes() == b"mine"
    assert artifacts.sha256_file(refs[20]) == ref20


def test_an_interrupted_run_for_earlier_snapshots_leaves_no_snapshot_and_resumes(small_data, tmp_path, monkeypatch):
    """The run making snapshots the model was past checkpoints into a hidden file, never under a snapshot's name,
    and the next call continues it to the same models."""
    from cdrb_cli.stages import train as stage
    from cdrb_cli.stages.train import earlier_path, train_or_resume

    demos, buffer = small_data

    def config(steps: int):
        return train_config(demos, buffer, "cdrb", tiny("cdrb", steps=steps, checkpoint_every=40, checkpoint_seconds=0))

    out = tmp_path / "long.h5"
    train(demos, buffer, config(80), out)
    ref20, ref60 = (
        train(demos, buffer, config(20), tmp_path / "r20.h5"),
        train(demos, buffer, config(60), tmp_path / "r60.h5"),
    )
    real, calls = stage._update, {"n": 0}

    def stopped_at_50(*a, **k):
        calls["n"] += 1
        if calls["n"] > 50:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(stage, "_update", stopped_at_50)
    with pytest.raises(KeyboardInterrupt):
        train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[20, 60])
    counted = {"n": 0}

    def counting(*a, **k):
        counted["n"] += 1
        return real(*a, **k)

    monkeypatch.setattr(stage, "_update", counting)
    assert not (tmp_path / "long.step60.h5").exists()  # nothing unfinished where an eval would take it
    side = artifacts.load(earlier_path(out, 60), "model").manifest.state
    assert side.step == 40 and not side.finished
    written = artifacts.load(tmp_path / "long.step20.h5", "model")  # written when the interrupted run passed it
    for k, v in _weights(ref20).items():
        np.testing.assert_array_equal(v, _weights(written)[k], err_msg=k)
    _, what = train_or_resume(demos, buffer, config(80), out, snapshots=[20, 60])
    assert what == "up to date, snapshots trained" and not earlier_path(out, 60).exists()
    assert counted["n"] == 60 - 40  # continued from the hidden checkpoint, not started over
    snap = artifacts.load(tmp_path / "long.step60.h5", "model")
    assert snap.manifest.config == ref60.manifest.config and snap.manifest.state.finished
    for k, v in _weights(ref60).items():
        np.testing.assert_array_equal(v, _weights(snap)[k], err_msg=k)


def _counting_updates(monkeypatch, stop_after: int | None = None) -> dict:
    """Count the training updates from here on (interrupting after ``stop_after`` of them, if given)."""
    from cdrb_cli.stages import train as stage

    real, calls = getattr(stage._update, "real", stage._update), {"n": 0}  # not an earlier counter

    def counted(*a, **k):
        calls["n"] += 1
        if stop_after is not None and calls["n"] > stop_after:
            raise KeyboardInterrupt
        return real(*a, **k)

    counted.real = real
    monkeypatch.setattr(stage, "_update", counted)
    return calls


def _same_weights(a, b) -> None:
    for k, v in _weights(a).items():
        np.testing.assert_array_equal(v, _weights(b)[k], err_msg=k)


def test_earlier_snapshots_recover_from_every_leftover_and_keep_what_is_done(small_data, tmp_path, monkeypatch):
    """What a killed or older run leaves is finished or continued, never trusted blindly: a finished hidden run
    killed before its rename becomes its snapshot (and a wider request still makes the rest); a hidden checkpoint
    of other settings is trained over from the start; an unfinished checkpoint under a snapshot's own name (where
    an older version trained it) is continued; a snapshot already there is not rewritten; another model under a
    snapshot's name is refused, --resume or not."""
    from cdrb_cli.stages import train as stage
    from cdrb_cli.stages.train import earlier_path, snapshot_path, train_or_resume

    demos, buffer = small_data

    def config(steps: int, seed: int = 0):
        settings = tiny("cdrb", steps=steps, checkpoint_every=40, checkpoint_seconds=0)
        return train_config(demos, buffer, "cdrb", settings, seed=seed)

    out, side = tmp_path / "long.h5", earlier_path(tmp_path / "long.h5", 60)
    train(demos, buffer, config(80), out)
    refs = {s: train(demos, buffer, config(s), tmp_path / f"r{s}.h5") for s in (20, 60)}

    def check(*steps: int) -> None:
        for s in steps:
            snap = artifacts.load(snapshot_path(out, s), "model")
            assert snap.manifest.config == refs[s].manifest.config and snap.manifest.state.finished
            _same_weights(refs[s], snap)

    # killed between finishing and renaming, then asked for more
    real_replace = stage.replace_file

    def killed(*a):
        raise KeyboardInterrupt

    monkeypatch.setattr(stage, "replace_file", killed)
    with pytest.raises(KeyboardInterrupt):
        train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[60])
    monkeypatch.setattr(stage, "replace_file", real_replace)
    assert artifacts.load(side, "model").manifest.state.finished and not snapshot_path(out, 60).exists()
    calls = _counting_updates(monkeypatch)
    _, what = train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[20, 60])
    assert what == "up to date, snapshots trained" and calls["n"] == 20 and not side.exists()
    check(20, 60)
    kept = {s: artifacts.sha256_file(snapshot_path(out, s)) for s in (20, 60)}

    # a hidden checkpoint of another seed: not continued
    snapshot_path(out, 60).unlink()
    _counting_updates(monkeypatch, stop_after=50)
    with pytest.raises(KeyboardInterrupt):
        train(demos, buffer, config(60, seed=1), side)
    calls = _counting_updates(monkeypatch)
    _, what = train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[20, 60])
    assert what == "up to date, snapshots trained" and calls["n"] == 60 and not side.exists()
    check(60)
    assert artifacts.sha256_file(snapshot_path(out, 20)) == kept[20]  # up to date: not rewritten

    # an unfinished checkpoint under the snapshot's own name, of this run: continued from where it stopped
    snapshot_path(out, 60).unlink()
    _counting_updates(monkeypatch, stop_after=50)
    with pytest.raises(KeyboardInterrupt):
        train(demos, buffer, config(60), snapshot_path(out, 60))
    assert artifacts.load(snapshot_path(out, 60), "model").manifest.state.step == 40
    calls = _counting_updates(monkeypatch)
    _, what = train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[20, 60])
    assert what == "up to date, snapshots trained" and calls["n"] == 60 - 40 and not side.exists()
    check(60)

    # a readable model of other settings under a snapshot's name: refused before any work, left as it is
    other = train(demos, buffer, config(20, seed=1), tmp_path / "other.h5")
    snapshot_path(out, 20).write_bytes(other.path.read_bytes())
    for resume in (False, True):
        with pytest.raises(BadInput) as err:
            train_or_resume(demos, buffer, config(80), out, resume=resume, snapshots=[20, 60])
        assert "long.step20.h5 exists and is not this run's snapshot" in err.value.message
        assert err.value.message.count(str(snapshot_path(out, 20))) == 1 and "retrains long.h5" in err.value.hint
    assert artifacts.sha256_file(snapshot_path(out, 20)) == artifacts.sha256_file(other.path)


def test_a_request_for_fewer_snapshots_keeps_the_hidden_work_of_one_for_more(small_data, tmp_path, monkeypatch):
    """Interrupted on its way to 60, a run for snapshots 20 and 60 leaves its checkpoint; asking for 20 alone
    trains 20 steps beside it, and asking for 60 again continues that checkpoint instead of starting over."""
    from cdrb_cli.stages.train import earlier_path, snapshot_path, train_or_resume

    demos, buffer = small_data

    def config(steps: int):
        return train_config(demos, buffer, "cdrb", tiny("cdrb", steps=steps, checkpoint_every=40, checkpoint_seconds=0))

    out = tmp_path / "long.h5"
    train(demos, buffer, config(80), out)
    _counting_updates(monkeypatch, stop_after=50)
    with pytest.raises(KeyboardInterrupt):
        train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[20, 60])
    snapshot_path(out, 20).unlink()  # e.g. removed by hand, then asked for again
    calls = _counting_updates(monkeypatch)
    train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[20])
    assert calls["n"] == 20 and artifacts.load(earlier_path(out, 60), "model").manifest.state.step == 40
    calls = _counting_updates(monkeypatch)
    _, what = train_or_resume(demos, buffer, config(80), out, resume=True, snapshots=[20, 60])
    assert what == "up to date, snapshots trained" and calls["n"] == 60 - 40
    assert not list(tmp_path.glob(".long.e*.h5"))
    ref = train(demos, buffer, config(60), tmp_path / "r60.h5")
    _same_weights(ref, artifacts.load(snapshot_path(out, 60), "model"))


def test_out_names_up_to_the_limit_train_with_and_without_snapshots(small_data, tmp_path):
    """The hidden checkpoint of earlier snapshots is claimed only when snapshots are asked for, and its name is
    shorter than its snapshot's, so any --out whose snapshot names fit trains."""
    from cdrb_cli.stages.train import train_or_resume

    demos, buffer = small_data
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=4))
    out = tmp_path / ("m" * 197 + ".h5")  # the longest name an output may have
    _, what = train_or_resume(demos, buffer, cfg, out)
    assert what == "trained" and artifacts.load(out, "model").manifest.state.finished
    out = tmp_path / ("n" * 190 + ".h5")  # its snapshot's name, n...n.step2.h5, is 199 bytes
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=4, checkpoint_every=2))
    _, what = train_or_resume(demos, buffer, cfg, out, snapshots=[2])
    assert what == "trained" and artifacts.load(tmp_path / ("n" * 190 + ".step2.h5"), "model").manifest.state.finished


def test_a_bad_snapshot_step_gets_a_hint_that_would_work(small_data):
    """The hint names a snapshot step that passes the same check, or, when no step below --steps can, the setting
    that moves where snapshots fall."""
    from cdrb_cli.stages.train import check_snapshots

    demos, _ = small_data
    for steps, every in ((200, 50), (30, 500), (30, 10)):
        cfg = train_config(demos, None, "mlp", {"steps": steps, "checkpoint_every": every})
        with pytest.raises(BadInput) as err:
            check_snapshots(cfg, [steps + 1])
        hint = err.value.hint
        if "e.g. --snapshot-at " in hint:
            assert check_snapshots(cfg, [int(hint.split()[-1])])
        else:
            assert steps <= 50 and "checkpoint_every" in hint


def test_state_action_ends_are_degraded_in_training_as_in_sampling(small_data, tmp_path):
    """With state-action features only the state part of the end states is pinned; sampling starts those ends
    from random buffer features, so training degrades their action part too (and keeps the state part exact)."""
    import torch

    from cdrb_cli.configs import ClusterConfig
    from cdrb_cli.methods.base import build_method
    from cdrb_cli.stages.cluster import cluster

    demos, _ = small_data
    buffer = cluster(demos, ClusterConfig(k=50, seed=0, features="state-action"), tmp_path / "b.h5")
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", features="state-action"))
    from cdrb_cli.stages.train import check_inputs

    method = build_method(cfg, demos.manifest.env, check_inputs(demos, buffer, "state-action"), buffer.points)
    assert method.kept == ()
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.uniform(-1, 1, size=(64, cfg.horizon, method.feature_dim)).astype(np.float32))
    start, goal = method.ends(x, method.obs_dim)
    y = method.pin(method._degrade(x, method.T - 1, rng), start, goal)
    o = method.obs_dim
    assert torch.equal(y[:, 0, :o], x[:, 0, :o]) and torch.equal(y[:, -1, :o], x[:, -1, :o])
    assert (y[:, 0, o:] != x[:, 0, o:]).any() and (y[:, -1, o:] != x[:, -1, o:]).any()
    state_cfg = train_config(demos, small_data[1], "cdrb", tiny("cdrb"))
    norm = check_inputs(demos, small_data[1], "state")
    assert build_method(state_cfg, demos.manifest.env, norm, small_data[1].points).kept == (0, -1)


def test_the_ema_copies_until_its_start_then_averages_every_n_steps():
    """The fused EMA update against its definition: a copy of every tensor (integer buffers included) up to
    ``ema_start``, then ``e <- d e + (1 - d) p`` on the parameters every ``ema_every`` steps, untouched between."""
    import copy
    import types

    import torch

    from cdrb_cli.stages.train import _ema_updater

    live = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
    avg = copy.deepcopy(live)
    cfg = types.SimpleNamespace(ema_start=2, ema_every=3, ema_decay=0.9)
    update = _ema_updater({"net": avg}, {"net": live}, cfg)

    def nudge():
        with torch.no_grad():
            for p in live.parameters():
                p.add_(torch.randn_like(p))
            live[1].num_batches_tracked += 5
            live[1].running_mean.add_(1.0)

    torch.manual_seed(0)
    for step in (1, 2):
        nudge()
        update(step)
        for (k, a), b in zip(avg.state_dict().items(), live.state_dict().values()):
            assert torch.equal(a, b), (step, k)
    before = [p.clone() for p in avg.parameters()]
    nudge()
    update(4)  # not a multiple of ema_every: nothing moves
    assert all(torch.equal(p, q) for p, q in zip(avg.parameters(), before))
    nudge()
    update(6)
    for e, old, p in zip(avg.parameters(), before, live.parameters()):
        assert torch.allclose(e, 0.9 * old + 0.1 * p, atol=1e-6)
        assert not torch.equal(e, p)


def test_inspect_plot_draws_a_models_training_curve(small_data, tmp_path, cdrb):
    demos, buffer = small_data
    model = tmp_path / "m.h5"
    train(demos, buffer, train_config(demos, buffer, "cdrb", tiny("cdrb", steps=20, checkpoint_every=10)), model)
    png = tmp_path / "curve.png"
    r = cdrb("inspect", model, "--plot", png)
    assert r.returncode == 0 and f"picture: {png}" in r.stderr, r.stderr
    assert png.stat().st_size > 5000
    r = cdrb("inspect", model, "--plot", png)  # an existing picture is kept unless --force
    assert r.returncode == 2 and "--plot" in r.stderr and r.stderr.count("\n") == 1
    assert cdrb("inspect", model, "--plot", png, "--force").returncode == 0
    r = cdrb("inspect", demos.path, "--plot", tmp_path / "d.png")
    assert r.returncode == 2 and "a demos artifact" in r.stderr and r.stderr.count("\n") == 1
    assert not (tmp_path / "d.png").exists() and r.stdout == ""


def test_a_network_too_big_for_memory_is_refused_before_allocating(small_data, tmp_path, cdrb):
    """Counted on the meta device: the dry run and the run itself refuse a U-Net whose training state alone exceeds
    the memory available (no 21 GB allocation attempted), in one line; a normal one reports its size."""
    demos, _ = small_data
    big = ["--set", "net.dim=4096", "--set", "net.dim_mults=8,8,8"]
    for extra in (["--dry-run"], ["--out", tmp_path / "big.h5"]):
        r = cdrb("train", demos.path, "--method", "diffuser", *big, *extra)
        assert r.returncode == 2 and "parameters: training needs at least" in r.stderr, r.stderr[-500:]
        assert r.stderr.count("\n") == 1 and r.stdout == ""
    assert not (tmp_path / "big.h5").exists()
    r = cdrb("train", demos.path, "--method", "diffuser", *TINY_FLAGS, "--dry-run")
    assert r.returncode == 0 and " parameters (about " in r.stderr


@pytest.mark.parametrize("name", ["cdrb", "diffuser"])
def test_start_weight_weighs_the_states_after_the_start(small_data, name):
    """start_weight against its definition (CDRB, and Diffuser predicting x0): with a network that predicts zeros,
    the loss is the mean over plan positions of the squared error, the start_span states after the pinned start
    weighted start_weight (the weights normalised to mean 1); 1 gives the plain mean (older models' loss)."""
    import torch

    from cdrb_cli.buffer import Normalizer
    from cdrb_cli.methods.base import build_method

    demos, buffer = small_data
    batch = torch.from_numpy(np.asarray(buffer.points[None, :16], dtype=np.float32)).repeat(4, 1, 1)
    for w, span in ((1.0, 4), (50.0, 4), (9.0, 2)):
        b = buffer if name == "cdrb" else None
        cfg = train_config(demos, b, name, tiny(name, **{"method.start_weight": w, "method.start_span": span}))
        method = build_method(cfg, demos.manifest.env, Normalizer(low=buffer.low, high=buffer.high), buffer.points)
        method.net = lambda x, k: torch.zeros_like(x)
        start, goal = method.ends(batch, method.obs_dim)
        sq = ((method.pin(torch.zeros_like(batch), start, goal) - batch) ** 2).mean(dim=(0, 2))  # per position
        weights = torch.ones(batch.shape[1])
        weights[1 : 1 + span] = w
        want = float((sq * weights).sum() / weights.sum())
        assert float(method.loss(batch, np.random.default_rng(0))) == pytest.approx(want, rel=1e-5)


def test_bookkeeping_settings_do_not_make_a_model_out_of_date(small_data, tmp_path):
    """A model is up to date for a config that differs only in when progress is saved (``checkpoint_seconds``),
    and out of date for one that changes what is computed."""
    demos, buffer = small_data
    cfg = train_config(demos, None, "mlp", tiny("mlp", steps=5, checkpoint_every=5, checkpoint_seconds=0))
    model = train(demos, None, cfg, tmp_path / "m.h5")
    parents = [demos]
    assert artifacts.existing(model.path, "model", cfg, parents).up_to_date
    assert artifacts.existing(
        model.path, "model", cfg.model_copy(update={"checkpoint_seconds": 60.0}), parents
    ).up_to_date
    other = artifacts.existing(model.path, "model", cfg.model_copy(update={"lr": 1e-2}), parents)
    assert other.status == "different" and "lr" in other.reason


def test_a_buffer_of_one_point_gives_no_ball_radius_unless_one_is_set(small_data):
    """CDRB's largest ball defaults to the buffer's diameter: a buffer whose states are one point gives none, which
    is one line naming --buffer, and a radius set by the user is used instead."""
    from cdrb_cli.methods.config import resolve_train_config
    from cdrb_cli.methods.registry import BufferInfo
    from cdrb_cli.settings import from_mapping

    demos, _ = small_data
    flat = BufferInfo(features="state", diameter=0.0)
    with pytest.raises(BadInput, match=r"^--buffer: gives cdrb's method.d_max = 0.0"):
        resolve_train_config(demos.manifest.env, flat, from_mapping({"method.name": "cdrb"}))
    cfg = resolve_train_config(demos.manifest.env, flat, from_mapping({"method.name": "cdrb", "method.d_max": 1.5}))
    assert cfg.method.d_max == 1.5


def test_d_max_from_the_data_box_is_the_diagonal_of_the_normalized_features(small_data):
    """``method.d_max_from = "data-box"`` (the official Fetch code's d_max): 2 per feature that varies, in quadrature,
    where the buffer's diameter is the default; a d_max set by the user wins over both."""
    from cdrb_cli.methods.config import buffer_info, resolve_train_config
    from cdrb_cli.settings import from_mapping

    demos, buffer = small_data
    info = buffer_info(buffer)
    varying = int((np.asarray(buffer.high) > np.asarray(buffer.low)).sum())
    assert varying >= 2 and info.box_diagonal == pytest.approx(2 * np.sqrt(varying))
    env = demos.manifest.env
    base = {"method.name": "cdrb"}
    assert resolve_train_config(env, info, from_mapping(base)).method.d_max == pytest.approx(info.diameter)
    box = resolve_train_config(env, info, from_mapping({**base, "method.d_max_from": "data-box"})).method
    assert box.d_max == pytest.approx(info.box_diagonal) and box.d_max > info.diameter
    set_too = {**base, "method.d_max_from": "data-box", "method.d_max": 1.5}
    assert resolve_train_config(env, info, from_mapping(set_too)).method.d_max == 1.5
    # `cdrb report` keeps such a model's row apart from the paper's CDRB
    from types import SimpleNamespace

    from cdrb_cli.methods.cdrb import CDRB

    def label(preset="paper", loss_weight_power=0.0, **method):
        method = SimpleNamespace(loss_weight_power=loss_weight_power, **method)
        return CDRB.variant(SimpleNamespace(config=SimpleNamespace(preset=preset, method=method)))

    assert label(ball="euclidean", d_max_from="buffer", geodesic_radii="matched") is None
    assert label(ball="euclidean", d_max_from="data-box", geodesic_radii="matched") == "d_max of the data box"
    geo = label(ball="geodesic", d_max_from="data-box", geodesic_radii="matched")
    assert geo == "geodesic balls, d_max of the data box"
    scaled = label(ball="geodesic", d_max_from="buffer", geodesic_radii="scaled")
    assert scaled == "geodesic balls, scaled radii"
    # a loss weight other than the preset's is named too (the quick preset weights by 1/eps_k, the paper's does not)
    official = label(ball="euclidean", d_max_from="data-box", geodesic_radii="matched", loss_weight_power=1.0)
    assert official == "d_max of the data box, 1/eps_k loss weight"
    assert (
        label(preset="quick", ball="euclidean", d_max_from="buffer", geodesic_radii="matched", loss_weight_power=1.0)
        is None
    )
    unweighted = label(preset="quick", ball="euclidean", d_max_from="buffer", geodesic_radii="matched")
    assert unweighted == "unweighted loss"
    squared = label(ball="euclidean", d_max_from="buffer", geodesic_radii="matched", loss_weight_power=2.0)
    assert squared == "loss weight (eps_1/eps_k)^2"


@pytest.mark.parametrize("name", ["cdrb", "mlp"])
def test_a_bfloat16_training_step_runs_the_network_in_bfloat16_and_keeps_float32_weights(small_data, name):
    """precision=bfloat16 runs a planner's training forward pass under autocast (its convolutions or linear layers
    give bfloat16), the logged loss is a float32 number close to the float32 step's, the weights stay float32."""
    import torch

    from cdrb_cli.methods.base import build_method
    from cdrb_cli.stages.train import check_inputs

    demos, buffer = small_data
    out = {}
    for precision in ("float32", "bfloat16"):
        cfg = train_config(demos, buffer, name, tiny(name, precision=precision, batch_size=32))
        torch.manual_seed(0)
        method = build_method(cfg, demos.manifest.env, check_inputs(demos, buffer, cfg.features), buffer.points)
        seen = []
        layers = [m for m in method.net.modules() if isinstance(m, (torch.nn.Conv1d, torch.nn.Linear))]
        hooks = [m.register_forward_hook(lambda mod, inp, o, seen=seen: seen.append(o.dtype)) for m in layers]
        batch = torch.from_numpy(method.data(demos, method.normalizer, "train").sample(32, np.random.default_rng(1)))
        loss = method.update(batch, np.random.default_rng(2), method.make_optimizers())
        for h in hooks:
            h.remove()
        assert set(seen) == {torch.bfloat16 if precision == "bfloat16" else torch.float32}
        assert all(p.dtype == torch.float32 for p in method.net.parameters())
        out[precision] = loss
    assert out["bfloat16"] == pytest.approx(out["float32"], rel=0.05)


def test_resume_messages_name_what_blocks_it_and_dry_run_checks_the_device(small_data, tmp_path, cdrb):
    """--resume lists only the settings that block continuing (a longer --steps does not), a file that is no model
    is named once without advising --force, and --dry-run refuses an unknown device as the run does."""
    from tests.factories import write

    demos, buffer = small_data
    args = ["train", demos.path, "--buffer", buffer.path, *TINY_FLAGS]
    out = tmp_path / "m.h5"
    assert cdrb(*args, "--steps", "20", "--out", out).returncode == 0
    r = cdrb(*args, "--steps", "40", "--set", "lr=0.1", "--resume", "--out", out)
    assert r.returncode == 2 and "other settings: lr" in r.stderr and "steps" not in r.stderr.split("settings:")[1]
    ev = write(tmp_path / "e.h5", "eval")
    r = cdrb(*args, "--steps", "40", "--resume", "--out", ev)
    assert r.returncode == 2 and r.stderr.count(str(ev)) == 1 and "--force" not in r.stderr, r.stderr
    r = cdrb(*args, "--steps", "5", "--dry-run", "--device", "mps")
    assert r.returncode == 2 and "--device mps: unknown device" in r.stderr, r.stderr
